"""BEM instances (``wsim.bem.instances``): bodies on one operator set stream its matrices once per
step for all of them. Stepped together they must move exactly as each moves alone (the products
differ only in summation order), free, loaded, on the ground and across a checkpoint."""

from __future__ import annotations

import numpy as np
import pytest

import wsim
from wsim.bem import build_operators, stepper

from bem_box import BOX, DT, G, MAT  # noqa: E402 (tests/ is on the path)

STEPS = 30


@pytest.fixture(scope="module")
def ops64():
    """The 26-node cube's operators stored in float64: the comparison then sees round-off only."""
    return build_operators(BOX, MAT, DT, precision="float64", cache=False, device="cpu")


def squeeze(t: float) -> np.ndarray:
    """A pressure pulse on the +x half of the cube's vertices (the first 15 ms), in frame axes [Pa]."""
    v = np.asarray(BOX.vertices)
    p = np.zeros_like(v)
    if t < 0.015:
        side = v[:, 0] > 0.05
        p[side, 0] = -2e4 * np.sin(np.pi * t / 0.015)
    return p


BODIES = [  # name, keyword arguments, loaded
    ("a", dict(position=(0.0, 1.0, 0.0), velocity=(0.5, 0.0, 0.0)), False),
    ("b", dict(position=(1.0, 1.0, 0.0), angular_velocity=(0.0, 3.0, 1.0)), True),
    ("c", dict(position=(2.0, 1.0, 0.0), velocity=(0.0, 0.2, -0.3), angular_velocity=(2.0, 0.0, 0.0)), False),
]


def make(world: wsim.World, ops, name: str, kw: dict, loaded: bool) -> wsim.BemBody:
    body = world.add(wsim.BemBody(BOX, MAT, DT, operators=ops, name=name, **kw))
    if loaded:
        body.add_traction(squeeze)
    return body


def sets_expected(device: str) -> bool:
    """Whether bodies on one operator set form a set here (numpy's BLAS on the CPU, a working
    CuPy on CUDA)."""
    dev = wsim.device.resolve_device(device)
    return stepper.resolve_backend("auto", dev) == "blas" or (dev.is_cuda and stepper._cupy_works(dev))


def trajectories(ops, device: str, together: bool, ground: bool, bodies_spec=BODIES) -> dict[str, np.ndarray]:
    """Each body's world points at every step (one World with all bodies, or one World each);
    under "umax:<name>" each body's largest vertex displacement in its frame at each step."""
    def new_world() -> wsim.World:
        w = wsim.World(fps=1.0 / DT, device=device, gravity=(0.0, -G, 0.0), body_contact=ground)
        if ground:
            w.add_collider(wsim.GroundPlane(height=0.895, friction=0.4))
        return w

    worlds = [new_world()] if together else []
    bodies = []
    for name, kw, loaded in bodies_spec:
        if not together:
            worlds.append(new_world())
        bodies.append(make(worlds[-1], ops, name, kw, loaded))
    out: dict[str, list] = {b.name: [] for b in bodies}
    umax: dict[str, list] = {f"umax:{b.name}": [] for b in bodies}
    for _ in range(STEPS):
        for w in worlds:
            w.step()
        for b in bodies:
            out[b.name].append(b.points())
            umax[f"umax:{b.name}"].append(np.abs(b.vertex_displacement()).max())
    if together and sets_expected(device):  # the bodies did step as one set
        assert all(b._set is not None and b._set is bodies[0]._set for b in bodies)
    return {k: np.array(v) for k, v in {**out, **umax}.items()}


def assert_same(a: dict, b: dict, tol: float) -> None:
    for name in a:
        assert np.max(np.abs(a[name] - b[name])) <= tol, (name, np.max(np.abs(a[name] - b[name])))


def no_one_body_passes(monkeypatch, device: str) -> None:
    """Where sets form (numpy's BLAS on the CPU, CuPy on CUDA) the set's products replace every
    body's own passes: make a one-body history pass an error."""
    if sets_expected(device):
        def one_body_pass(*a, **k):
            raise AssertionError("a one-body history pass ran inside an instance set")

        monkeypatch.setattr(stepper, "history", one_body_pass)


def test_free_and_loaded_instances_move_as_alone(ops64, device, monkeypatch):
    """Three cubes on one operator set, free in gravity (one spun, one squeezed by a traction pulse):
    stepped as one set (no one-body pass runs) they follow their solo runs to round-off."""
    alone = trajectories(ops64, device, together=False, ground=False)
    no_one_body_passes(monkeypatch, device)
    together = trajectories(ops64, device, together=True, ground=False)
    monkeypatch.undo()
    assert_same(alone, together, 1e-12)
    # the bodies did move and deform: the squeezed one deforms far more than the free ones, and
    # all fall
    assert together["umax:b"].max() > 10.0 * max(together["umax:a"].max(), together["umax:c"].max())
    assert all(together[n][-1, :, 1].mean() < together[n][0, :, 1].mean() for n in "abc")


def test_mixed_members_move_as_alone(ops64, device):
    """Members that cannot finish with the set (no frame update, no error correction, held
    points) share its products and finish on their own: each still moves as alone."""
    spec = [
        ("a", dict(position=(0.0, 1.0, 0.0), velocity=(0.5, 0.0, 0.0), frame_update=False), True),
        ("b", dict(position=(1.0, 1.0, 0.0), angular_velocity=(0.0, 3.0, 1.0), error_correction=False), False),
        ("c", dict(position=(2.0, 1.0, 0.0), angular_velocity=(2.0, 0.0, 0.0)), False),
        ("d", dict(position=(3.0, 1.0, 0.0), velocity=(0.0, 0.2, -0.3)), True),
    ]
    alone = trajectories(ops64, device, together=False, ground=False, bodies_spec=spec)
    together = trajectories(ops64, device, together=True, ground=False, bodies_spec=spec)
    assert_same(alone, together, 1e-12)


def test_instances_in_a_contact_group_land_as_alone(ops64, device, monkeypatch):
    """With contact on (every BEM body of one dt in one group) the set predicts before each
    constraint solve: three cubes dropped 5 mm onto the ground, apart, match their solo landings."""
    alone = trajectories(ops64, device, together=False, ground=True)
    no_one_body_passes(monkeypatch, device)
    together = trajectories(ops64, device, together=True, ground=True)
    monkeypatch.undo()
    assert_same(alone, together, 1e-9)
    # each fell the 5 mm onto the ground (at 0.895 m) and stands on it
    for n in "abc":
        assert abs(together[n][-1, :, 1].min() - 0.895) < 5e-4, n


def test_float32_instances_track_alone(box_ops):
    """The default float32 storage: the same within float32 round-off of the summation order."""
    alone = trajectories(box_ops, "cpu", together=False, ground=False)
    together = trajectories(box_ops, "cpu", together=True, ground=False)
    assert_same(alone, together, 1e-7)  # 3.7e-9 m here


def test_instances_continue_from_a_checkpoint(ops64, tmp_path):
    """The rings are views of the set's arrays: a restore writes into them, and the run goes on
    exactly as it went the first time."""
    world = wsim.World(fps=1.0 / DT, device="cpu", gravity=(0.0, -G, 0.0), body_contact=False)
    bodies = [make(world, ops64, name, kw, loaded) for name, kw, loaded in BODIES]
    for _ in range(5):
        world.step()
    path = world.checkpoint(tmp_path / "five.h5")
    for _ in range(10):
        world.step()
    first = [b.points() for b in bodies]
    assert world.restore(path) == 5
    for _ in range(10):
        world.step()
    for b, x in zip(bodies, first):
        assert np.array_equal(b.points(), x), b.name
