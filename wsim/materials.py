"""Elastic materials, validated once.

``ElasticMaterial`` holds an isotropic linear-elastic solid: Young's modulus E [Pa] (or the shear
modulus mu [Pa] instead), Poisson's ratio nu [-] and density rho [kg/m^3]. It derives the Lamé
parameters, bulk modulus and the P- and S-wave speeds every method needs (the BEM kernels use
c1, c2; PBD maps E, K to compliances; EoL uses lambda, mu).

``body_material`` is how a body constructor takes its material: an ``ElasticMaterial``, or a dict
of its arguments checked here so that a bad value is reported with the body's name.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from wsim.errors import InvalidMaterial, InvalidParameter
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
        # the default name says nothing: name the constructor (a body cannot be named here, it does
        # not exist yet; a dict material given to a body is checked with the body's name)
        E_f, nu_f, rho_f = _checked("ElasticMaterial" if name == "material" else f"material '{name}'",
                                    E, nu, rho, mu, incompressible)
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


def body_material(material: Any, body: str, default: ElasticMaterial | None = None) -> ElasticMaterial:
    """The material given to body ``body``'s constructor, as an ``ElasticMaterial``.

    ``material`` is an ``ElasticMaterial`` (used as is: it was checked when it was made), a dict of
    ``ElasticMaterial``'s keyword arguments (``dict(E=1e5, nu=0.3, rho=1000.0)``), checked here so
    that every problem names the body (``body 'neck': material: Young's modulus E = -1.0 Pa must be
    > 0``), or None for ``default`` where the body has one.

    Raises:
        InvalidMaterial: a value out of range, or a key that is not an argument of ElasticMaterial.
        InvalidParameter: anything else (not a material), naming the body.
    """
    if material is None and default is not None:
        return default
    if isinstance(material, ElasticMaterial):
        return material
    if not isinstance(material, Mapping):
        raise InvalidParameter(f"body '{body}': material must be a wsim.ElasticMaterial or a dict of its arguments "
                               f"(E or mu, nu, rho), got {type(material).__name__}")
    kwargs = dict(material)
    name = kwargs.get("name")
    p = f"body '{body}': material" + ("" if name is None else f" '{name}'")
    try:
        args = inspect.signature(ElasticMaterial).bind(**kwargs)
    except TypeError as exc:  # a key that is no argument of ElasticMaterial
        raise InvalidMaterial(f"{p}: {exc}; the arguments are E or mu, nu, rho, incompressible, name") from None
    args.apply_defaults()  # the defaults live in ElasticMaterial.__init__ only
    a = args.arguments
    _checked(p, a["E"], a["nu"], a["rho"], a["mu"], a["incompressible"])
    return ElasticMaterial(**kwargs)


def _checked(p: str, E: object, nu: object, rho: object, mu: object, incompressible: bool) -> tuple[float, float, float]:
    """(E, nu, rho) as finite floats in their physical ranges, or InvalidMaterial whose message starts
    with ``p`` (``material 'rubber'``, or ``body 'neck': material`` from ``body_material``)."""
    nu_f = finite_number(nu, f"{p}: Poisson's ratio nu", InvalidMaterial)
    rho_f = finite_number(rho, f"{p}: density rho [kg/m^3]", InvalidMaterial)
    if (E is None) == (mu is None):
        raise InvalidMaterial(f"{p}: give exactly one of Young's modulus E or shear modulus mu")
    if incompressible:
        if nu_f != 0.5:
            raise InvalidMaterial(
                f"{p}: incompressible=True needs nu = 0.5, got nu = {nu_f}"
            )
    elif not (-1.0 < nu_f < 0.5):
        hint = " (pass incompressible=True for the nu = 0.5 limit)" if nu_f == 0.5 else ""
        raise InvalidMaterial(f"{p}: Poisson's ratio nu = {nu_f} must lie in (-1, 0.5){hint}")
    if E is not None:
        E_f = finite_number(E, f"{p}: Young's modulus E [Pa]", InvalidMaterial)
        if E_f <= 0.0:
            raise InvalidMaterial(f"{p}: Young's modulus E = {E_f} Pa must be > 0")
    else:
        mu_f = finite_number(mu, f"{p}: shear modulus mu [Pa]", InvalidMaterial)
        if mu_f <= 0.0:
            raise InvalidMaterial(f"{p}: shear modulus mu = {mu_f} Pa must be > 0")
        E_f = 2.0 * mu_f * (1.0 + nu_f)
    if rho_f <= 0.0:
        raise InvalidMaterial(f"{p}: density rho = {rho_f} kg/m^3 must be > 0")
    return E_f, nu_f, rho_f
