"""Surface-only elastodynamic BEM (Sugimoto, Batty, Hachisuka): kernels, convolution quadrature, operators.

Public entry points:

- :func:`laplace_matrices` / :func:`laplace_operators`: H, G (and D, Q) at one complex frequency s;
- :func:`build_operators`: the time-domain operator set of one body for a time step (cached);
- :class:`Quadrature`: the quadrature knobs; :func:`prepare_surface`: mesh validation and double nodes;
- :func:`mass_properties`: mass, centre of mass and inertia from surface integrals;
- :func:`decompose`: a body of closed subdomains joined at their interfaces (domain decomposition).
"""

from wsim.bem.assembly import LaplaceOperators, laplace_matrices, laplace_operators
from wsim.bem.decompose import decompose
from wsim.bem.mass import MassProperties, mass_properties
from wsim.bem.operators import BemOperators, build_operators
from wsim.bem.quadrature import Quadrature
from wsim.bem.surface import BemSurface, prepare_surface

__all__ = [
    "BemOperators",
    "BemSurface",
    "LaplaceOperators",
    "MassProperties",
    "Quadrature",
    "build_operators",
    "decompose",
    "laplace_matrices",
    "laplace_operators",
    "mass_properties",
    "prepare_surface",
]
