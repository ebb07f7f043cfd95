"""Elastic materials, validated once.

``ElasticMaterial`` holds an isotropic linear-elastic solid: Young's modulus E [Pa] (or the shear
modulus mu [Pa] instead), Poisson's ratio nu [-] and density rho [kg/m^3]. It derives the Lamé
parameters, bulk modulus and the P- and S-wave speeds every method needs (the BEM kernels use
c1, c2; PBD maps E, K to compliances; EoL uses lambda, mu).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from wsim.errors import InvalidMaterial
from wsim.validate import finite_number


@dataclass(frozen=True, init=False)
class ElasticMaterial:
    """Isotropic linear-elastic material.

    Args:
        E: Young's modulus [Pa], > 0. Give either ``E`` or ``mu``.
        nu: Poisson's ratio [-], in (-1, 0.5); 0.5 only with ``incompressible=True``.
        rho: density [kg/m^3], > 0.
        mu: shear modulus [Pa], > 0, instead of ``E`` (E = 2 mu (1 + nu)).
        incompressible: ask for the nu = 0.5 limit explicitly (lambda, K and c1 are infinite).
        name: used in error messages.
    """

    E: float
    nu: float
    rho: float
    incompressible: bool = False
    name: str = field(default="material", compare=False)

    def __init__(
        self,
        E: float | None = None,
        nu: float = 0.3,
        rho: float = 1000.0,
        *,
        mu: float | None = None,
        incompressible: bool = False,
        name: str = "material",
    ) -> None:
        nu_f = finite_number(nu, f"material '{name}': Poisson's ratio nu", InvalidMaterial)
        rho_f = finite_number(rho, f"material '{name}': density rho [kg/m^3]", InvalidMaterial)
        if (E is None) == (mu is None):
            raise InvalidMaterial(f"material '{name}': give exactly one of Young's modulus E or shear modulus mu")
        if incompressible:
            if nu_f != 0.5:
                raise InvalidMaterial(
                    f"material '{name}': incompressible=True needs nu = 0.5, got nu = {nu_f}"
                )
        elif not (-1.0 < nu_f < 0.5):
            hint = " (pass incompressible=True for the nu = 0.5 limit)" if nu_f == 0.5 else ""
            raise InvalidMaterial(f"material '{name}': Poisson's ratio nu = {nu_f} must lie in (-1, 0.5){hint}")
        if E is not None:
            E_f = finite_number(E, f"material '{name}': Young's modulus E [Pa]", InvalidMaterial)
            if E_f <= 0.0:
                raise InvalidMaterial(f"material '{name}': Young's modulus E = {E_f} Pa must be > 0")
        else:
            mu_f = finite_number(mu, f"material '{name}': shear modulus mu [Pa]", InvalidMaterial)
            if mu_f <= 0.0:
                raise InvalidMaterial(f"material '{name}': shear modulus mu = {mu_f} Pa must be > 0")
            E_f = 2.0 * mu_f * (1.0 + nu_f)
        if rho_f <= 0.0:
            raise InvalidMaterial(f"material '{name}': density rho = {rho_f} kg/m^3 must be > 0")
        object.__setattr__(self, "E", E_f)
        object.__setattr__(self, "nu", nu_f)
        object.__setattr__(self, "rho", rho_f)
        object.__setattr__(self, "incompressible", bool(incompressible))
        object.__setattr__(self, "name", str(name))

    @property
    def mu(self) -> float:
        """Shear modulus (second Lamé parameter) [Pa]."""
        return self.E / (2.0 * (1.0 + self.nu))

    @property
    def lam(self) -> float:
        """First Lamé parameter lambda [Pa]; inf in the incompressible limit."""
        if self.incompressible:
            return math.inf
        return self.E * self.nu / ((1.0 + self.nu) * (1.0 - 2.0 * self.nu))

    @property
    def bulk_modulus(self) -> float:
        """Bulk modulus K = lambda + 2 mu / 3 [Pa]; inf in the incompressible limit."""
        if self.incompressible:
            return math.inf
        return self.E / (3.0 * (1.0 - 2.0 * self.nu))

    @property
    def c1(self) -> float:
        """P-wave (dilatational) speed sqrt((lambda + 2 mu) / rho) [m/s]; inf if incompressible."""
        return math.sqrt((self.lam + 2.0 * self.mu) / self.rho)

    @property
    def c2(self) -> float:
        """S-wave (shear) speed sqrt(mu / rho) [m/s]."""
        return math.sqrt(self.mu / self.rho)

    def as_key(self) -> dict[str, float | bool]:
        """The parameters that define the material, for operator cache keys."""
        return {"E": self.E, "nu": self.nu, "rho": self.rho, "incompressible": self.incompressible}
