"""Closed-form elastodynamic results for a solid sphere, used to validate BEM bodies.

A homogeneous isotropic solid sphere of radius a under uniform surface pressure P:

* static: u_r(a) = -P a / (3 lambda + 2 mu) = -P a / (3 K);
* free radial (breathing) vibration: u_r = A j_1(k r) with k = omega / c1; a traction-free
  surface gives the frequency equation xi cot xi = 1 - (c1 / (2 c2))^2 xi^2, xi = omega a / c1
  (Love, "A Treatise on the Mathematical Theory of Elasticity", Sec. 195).
"""

from __future__ import annotations

import math

from scipy.optimize import brentq

from wsim.errors import InvalidParameter
from wsim.materials import ElasticMaterial


def breathing_xi(material: ElasticMaterial, mode: int = 0) -> float:
    """The (mode + 1)-th positive root xi of xi cot xi = 1 - (c1 / (2 c2))^2 xi^2."""
    if material.incompressible:
        raise InvalidParameter("an incompressible sphere has no breathing mode (c1 is infinite)")
    beta = (material.c1 / (2.0 * material.c2)) ** 2

    def f(xi: float) -> float:  # multiplied by sin(xi): continuous on each (m pi, (m+1) pi)
        return xi * math.cos(xi) - (1.0 - beta * xi * xi) * math.sin(xi)

    # f ~ (beta - 1/3) xi^3 > 0 near 0 (beta >= 1/2 for nu >= 0): start clear of the trivial root
    lo, hi = mode * math.pi + 0.05, (mode + 1) * math.pi - 1e-9
    return brentq(f, lo, hi, xtol=1e-14)


def breathing_frequency(material: ElasticMaterial, radius: float, mode: int = 0) -> float:
    """Angular frequency omega [rad/s] of the sphere's (mode + 1)-th breathing mode."""
    return breathing_xi(material, mode) * material.c1 / radius


def static_radial_displacement(material: ElasticMaterial, radius: float, pressure: float) -> float:
    """u_r(a) [m] of a solid sphere under uniform pressure P [Pa] (compressive P > 0 gives u_r < 0)."""
    return -pressure * radius / (3.0 * material.bulk_modulus)
