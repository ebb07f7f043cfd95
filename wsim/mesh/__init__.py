"""Surface meshes for wsim, one module per job:

* :mod:`~wsim.mesh.surface` -- array input (``surface_arrays``, with ``merge_vertices``), mesh files
  (``load``, ``load_fitted``), measures (``signed_volume``, ``face_areas``, ``vertex_normals``,
  ``vertex_areas``) and vertices at the same position (``merge_coincident_vertices``);
* :mod:`~wsim.mesh.stage` -- ``load_usd``: a ``UsdGeom.Mesh`` prim of a USD stage (``load`` also
  takes ``file.usd:/World/prim``), in metres, Y up, outward faces, with its texture coordinates;
* :mod:`~wsim.mesh.validate` -- ``check_surface``: every defect raised with an example index (and,
  for a body, several pieces; split vertices get a hint to merge them);
* :mod:`~wsim.mesh.topology` -- ``edges``, ``hinges``, ``has_boundary``, ``watertight``, ``pieces``;
* :mod:`~wsim.mesh.shapes` -- procedural shapes for scenes, tools and tests;
* :mod:`~wsim.mesh.inside` -- the one point-in-mesh test (``inside_surface``, ``SurfaceQuery``) and the contact kernels' choice of test (``inside_test``)
  and the winding-number field (``winding_number``);
* :mod:`~wsim.mesh.tets` -- ``tetrahedralize`` for ``PbdBody(tets="auto")`` (not named after the
  function, which would shadow the module as a package attribute).

Conventions used throughout (and expected by every caller):

* vertices are ``float64`` arrays of shape ``(N, 3)``, in metres;
* faces are ``int32`` arrays of shape ``(M, 3)``, listed counter-clockwise when seen from outside,
  so the right-hand-rule normals point outwards and the signed volume is positive;
* every problem with a mesh raises :class:`wsim.errors.InvalidMesh` whose message starts with
  the object's name -- ``"mesh '<name>': "`` for a bare name, or the caller's own label verbatim
  when it is already quoted (``name="body 'horse'"`` gives ``"body 'horse': "``) -- and names the
  offending quantity together with an example index, so a scene script can be fixed from the
  message alone.
"""

from wsim.mesh.inside import SurfaceQuery, inside_surface, inside_test, winding_number
from wsim.mesh.shapes import beam, bumpy_cube, bumpy_sphere, fish, neck_body, neck_pose, torus
from wsim.mesh.stage import load_usd
from wsim.mesh.surface import (
    display_name,
    face_areas,
    face_colors,
    face_uvs,
    load,
    load_fitted,
    merge_coincident_vertices,
    signed_volume,
    surface_arrays,
    vertex_areas,
    vertex_normals,
)
from wsim.mesh.tets import tetrahedralize
from wsim.mesh.topology import edges, has_boundary, hinges, pieces, watertight
from wsim.mesh.validate import check_surface

__all__ = [
    "surface_arrays",
    "load",
    "load_usd",
    "display_name",
    "face_colors",
    "face_uvs",
    "load_fitted",
    "signed_volume",
    "face_areas",
    "vertex_normals",
    "vertex_areas",
    "check_surface",
    "edges",
    "hinges",
    "has_boundary",
    "watertight",
    "pieces",
    "merge_coincident_vertices",
    "bumpy_sphere",
    "fish",
    "neck_body",
    "neck_pose",
    "beam",
    "torus",
    "bumpy_cube",
    "inside_surface",
    "inside_test",
    "SurfaceQuery",
    "winding_number",
    "tetrahedralize",
]
