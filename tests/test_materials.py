"""ElasticMaterial: derived moduli against their definitions, and validation."""

from __future__ import annotations

import math

import pytest

import wsim


def test_lame_parameters_and_wave_speeds():
    m = wsim.ElasticMaterial(E=2.0e6, nu=0.25, rho=1200.0)
    lam, mu = m.lam, m.mu
    # invert the textbook relations: E = mu (3 lam + 2 mu) / (lam + mu), nu = lam / (2 (lam + mu))
    assert mu * (3 * lam + 2 * mu) / (lam + mu) == pytest.approx(2.0e6, rel=1e-12)
    assert lam / (2 * (lam + mu)) == pytest.approx(0.25, rel=1e-12)
    assert m.bulk_modulus == pytest.approx(lam + 2 * mu / 3, rel=1e-12)
    assert m.c1 == pytest.approx(math.sqrt((lam + 2 * mu) / 1200.0), rel=1e-12)
    assert m.c2 == pytest.approx(math.sqrt(mu / 1200.0), rel=1e-12)
    # nu = 0.25 gives lam = mu and c1/c2 = sqrt(3)
    assert lam == pytest.approx(mu, rel=1e-12)
    assert m.c1 / m.c2 == pytest.approx(math.sqrt(3.0), rel=1e-12)


def test_shear_modulus_instead_of_young():
    a = wsim.ElasticMaterial(mu=4.0e4, nu=0.3, rho=1000.0)
    assert a.mu == pytest.approx(4.0e4, rel=1e-12)
    assert a.E == pytest.approx(2 * 4.0e4 * 1.3, rel=1e-12)
    assert a == wsim.ElasticMaterial(E=a.E, nu=0.3, rho=1000.0)


def test_incompressible_limit_is_explicit():
    m = wsim.ElasticMaterial(E=1e5, nu=0.5, rho=1000.0, incompressible=True)
    assert math.isinf(m.lam) and math.isinf(m.bulk_modulus) and math.isinf(m.c1)
    assert m.mu == pytest.approx(1e5 / 3.0)
    with pytest.raises(wsim.InvalidMaterial, match="incompressible=True"):
        wsim.ElasticMaterial(E=1e5, nu=0.5, rho=1000.0)


@pytest.mark.parametrize(
    "kwargs, words",
    [
        (dict(E=0.0, nu=0.3, rho=1000.0), "Young's modulus E = 0.0 Pa must be > 0"),
        (dict(E=-5.0, nu=0.3, rho=1000.0), "Young's modulus"),
        (dict(E=1e5, nu=0.3, rho=0.0), "density rho = 0.0"),
        (dict(E=1e5, nu=0.3, rho=-1.0), "density"),
        (dict(E=1e5, nu=0.55, rho=1000.0), "Poisson's ratio nu = 0.55"),
        (dict(E=1e5, nu=-1.0, rho=1000.0), "Poisson's ratio nu = -1.0"),
        (dict(E=1e5, nu=float("nan"), rho=1000.0), "not finite"),
        (dict(E=1e5, mu=1e4, nu=0.3, rho=1000.0), "exactly one of"),
        (dict(mu=-1.0, nu=0.3, rho=1000.0), "shear modulus"),
        (dict(E="soft", nu=0.3, rho=1000.0), "must be a number"),
    ],
)
def test_invalid_materials_are_named(kwargs, words):
    with pytest.raises(wsim.InvalidMaterial) as info:
        wsim.ElasticMaterial(**kwargs, name="rubber")
    assert "rubber" in str(info.value) and words in str(info.value)
