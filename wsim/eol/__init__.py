"""Eulerian-on-Lagrangian solids (Fan, Litven, Levin, Pai): grid, Lagrangian coordinates, momentum split.

``EolBody`` (``body``) is the World body built from these pieces, with contact (``contact``) and
plasticity; its per-instance state is one ``EolState`` (``state``). The pieces: the intermediate-domain grid and its
material quadrature (``grid``), the rigid and affine Lagrangian coordinates with the mass blocks
of Eq. (11) (``lagrangian``), the least-squares momentum split of Eqs. (23-25) (``split``), and
Neo-Hookean elastic forces from the reference map on the grid (``elastic``), and semi-Lagrangian
or BFECC advection of nodal fields (``advection``), both Warp kernels, and the adaptive time step
of Eqs. (30-33) (``timestep``), and surface tracking by Algorithm 2 (``tracking``, a Warp kernel).
"""

from wsim.eol.body import EolBody, Plasticity
from wsim.eol.grid import EolGrid, MaterialSamples, lumped_masses, make_grid, material_samples
from wsim.eol.lagrangian import KINDS, MassBlocks, consistent_blocks, lagrangian_jacobian, mass_blocks
from wsim.eol.split import momentum_split
from wsim.eol.state import EolState

__all__ = [
    "EolBody", "EolState", "Plasticity", "EolGrid", "MaterialSamples", "MassBlocks", "KINDS", "consistent_blocks", "lagrangian_jacobian",
    "lumped_masses", "make_grid", "mass_blocks", "material_samples", "momentum_split",
]
