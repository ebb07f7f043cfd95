"""The knob studies of ``wsim study`` (``wsim.study``): one scene file per method, each declaring its
knob grid (``SPEC``: quick and full sizes, default, high-accuracy reference).

- ``bem``: time step, CQ method, precision, compression, quadrature, mesh.
- ``eol``: grid resolution, advection scheme, CFL number, step cap.
- ``pbd``: substeps, iterations, mesh.
- ``pde``: PDE reconstruction's keyframe stride, basis and curve length.
- ``coupling``: the World's coupling interval between methods.
"""
