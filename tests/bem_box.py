"""The small BEM cube the constraint and contact tests share (26 nodes: a CPU operator build of
seconds); its operators come from the session fixture ``box_ops`` in ``conftest.py``."""

from __future__ import annotations

import trimesh

import wsim

G = 9.81
DT = 2e-3
MAT = wsim.ElasticMaterial(E=1.0e6, nu=0.3, rho=1000.0)
BOX = trimesh.creation.box(extents=(0.2, 0.2, 0.2)).subdivide()
