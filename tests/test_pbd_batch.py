"""PBD batches (``wsim.pbd.batch``): bodies stepped in one launch set move exactly as each moves
alone: free, spinning (the per-body momentum restoration), on the ground, through a frame where
two of them touch (the batch then steps its members one by one), and across a checkpoint."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

import wsim
from wsim.pbd import batch as pbd_batch

FRAMES = 12


def ball(radius: float, subdivisions: int) -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)


SPEC = [  # name, mesh, keyword arguments
    ("a", ball(0.2, 1), dict(position=(0.0, 0.6, 0.0), velocity=(0.5, 0.0, 0.0), tets="auto")),
    ("b", ball(0.15, 2), dict(position=(1.0, 0.8, 0.0), angular_velocity=(0.0, 4.0, 1.0), tets="auto")),
    ("c", ball(0.25, 1), dict(position=(2.5, 1.0, 0.0), angular_velocity=(3.0, 0.0, 0.0), velocity=(0.0, 1.0, 0.0),
                              tets="auto")),
]


def run(device: str, together: bool, *, gravity=(0.0, -9.81, 0.0), ground: bool = True, contact: bool = False,
        spec=SPEC, frames: int = FRAMES, batches: bool = True) -> dict[str, np.ndarray]:
    """Every body's particles after each frame, the bodies in one World or one World each."""
    def world() -> wsim.World:
        w = wsim.World(fps=30.0, device=device, gravity=gravity, body_contact=contact)
        if ground:
            w.add_collider(wsim.GroundPlane(friction=0.5))
        return w

    worlds = [world()] if together else []
    bodies = []
    for name, mesh, kw in spec:
        if not together:
            worlds.append(world())
        bodies.append(worlds[-1].add(wsim.PbdBody(mesh, dict(E=2e5, nu=0.3, rho=500.0), name=name, **kw)))
    original = pbd_batch.batches
    if not batches:
        pbd_batch.batches = lambda bodies: []
    try:
        out: dict[str, list] = {b.name: [] for b in bodies}
        for _ in range(frames):
            for w in worlds:
                w.step()
            for b in bodies:
                out[b.name].append(b.particles())
    finally:
        pbd_batch.batches = original
    if together and batches:  # they did form one batch
        assert all(b._batch is not None and b._batch is bodies[0]._batch for b in bodies)
    return {k: np.array(v) for k, v in out.items()}


def assert_same(a: dict, b: dict, tol: float) -> None:
    for name in a:
        assert np.max(np.abs(a[name] - b[name])) <= tol, (name, np.max(np.abs(a[name] - b[name])))


@pytest.mark.parametrize("contact", [False, True])
def test_batched_bodies_move_as_alone(device, contact, monkeypatch):
    """Free falls onto the ground, spins and throws: the batch (stepped by the World, or inside
    the lockstep of touching-capable bodies with contact on) gives each body its solo trajectory:
    the same arithmetic (bit for bit on the CPU), the momentum restoration summed per body."""
    alone = run(device, together=False, contact=contact)
    real = wsim.PbdBody.advance

    def solo(body, t0, t1):  # after the first frame (which forms the batch) no body steps alone
        if body._batch is not None:
            raise AssertionError(f"body '{body.name}' stepped alone while in a batch")
        real(body, t0, t1)

    monkeypatch.setattr(wsim.PbdBody, "advance", solo)
    together = run(device, together=True, contact=contact)
    monkeypatch.undo()
    assert_same(alone, together, 1e-6)  # float32 positions; atomic sums on a GPU
    assert together["b"][-1][:, 1].min() > -0.01  # the ground held them


def test_batched_spin_keeps_each_bodys_angular_momentum(device):
    """No gravity, no ground: every body keeps its own momentum and angular momentum; a mix-up of
    the per-body sums would move one body's spin to another."""
    alone = run(device, together=False, gravity=(0.0, 0.0, 0.0), ground=False)
    together = run(device, together=True, gravity=(0.0, 0.0, 0.0), ground=False)
    assert_same(alone, together, 1e-6)


def test_members_of_mixed_families_and_settings_move_as_alone():
    """Members with different constraint families (bending on one, no stretch on another), mass,
    pinned particles and no momentum restoration: each keeps its own projection order and
    settings inside the batch (bit for bit on the CPU)."""
    spec = [("a", ball(0.2, 1), dict(position=(0.0, 0.6, 0.0), tets="auto", stretch=False)),
            ("b", ball(0.2, 1), dict(position=(1.0, 0.6, 0.0), tets="auto", bending=True, angular_velocity=(0, 3, 0))),
            ("c", ball(0.2, 1), dict(position=(2.0, 0.6, 0.0), tets="auto", mass=3.0, conserve_angular_momentum=False,
                                     angular_velocity=(2, 0, 0))),
            ("d", ball(0.2, 1), dict(position=(3.0, 0.6, 0.0), tets="auto", pinned=[0, 1]))]
    alone = run("cpu", together=False, spec=spec)
    together = run("cpu", together=True, spec=spec)
    assert_same(alone, together, 0.0)


def test_a_frame_of_touching_steps_the_members_alone():
    """Two balls thrown at each other with contact on: in the frames they touch, the batch steps
    its members one by one through the lockstep; the result is the run without batches."""
    spec = [("a", ball(0.2, 1), dict(position=(-0.3, 0.5, 0.0), velocity=(2.0, 0.0, 0.0), tets="auto")),
            ("b", ball(0.2, 1), dict(position=(0.3, 0.5, 0.0), velocity=(-2.0, 0.0, 0.0), tets="auto")),
            ("c", ball(0.2, 1), dict(position=(3.0, 0.5, 0.0), tets="auto"))]
    plain = run("cpu", together=True, contact=True, spec=spec, batches=False)
    batched = run("cpu", together=True, contact=True, spec=spec)
    assert_same(plain, batched, 1e-6)
    assert batched["a"][-1][:, 0].mean() < batched["b"][-1][:, 0].mean()  # they bounced, not passed


def test_batch_continues_from_a_checkpoint(tmp_path):
    world = wsim.World(fps=30.0, device="cpu", gravity=(0.0, -9.81, 0.0), body_contact=False)
    world.add_collider(wsim.GroundPlane())
    bodies = [world.add(wsim.PbdBody(mesh, name=name, **kw)) for name, mesh, kw in SPEC]
    for _ in range(4):
        world.step()
    assert bodies[0]._batch is not None
    path = world.checkpoint(tmp_path / "four.h5")
    for _ in range(5):
        world.step()
    first = [b.particles() for b in bodies]
    assert world.restore(path) == 4
    for _ in range(5):
        world.step()
    for b, x in zip(bodies, first):
        assert np.array_equal(b.particles(), x), b.name


def test_bodies_with_other_settings_step_alone():
    world = wsim.World(fps=30.0, device="cpu", body_contact=False)
    a = world.add(wsim.PbdBody(ball(0.2, 1), name="a", tets="auto"))
    b = world.add(wsim.PbdBody(ball(0.2, 1), name="b", position=(1.0, 0.0, 0.0), tets="auto"))
    c = world.add(wsim.PbdBody(ball(0.2, 1), name="c", position=(2.0, 0.0, 0.0), tets="auto", iterations=3))
    d = world.add(wsim.PbdBody(ball(0.2, 1), name="d", position=(3.0, 0.0, 0.0)))  # a surface body: its volume
    world.step()
    assert a._batch is b._batch is not None and c._batch is None and d._batch is None


def test_a_diverged_member_is_named():
    """The batch checks all members in one launch; a non-finite member is then found and named."""
    world = wsim.World(fps=30.0, device="cpu", body_contact=False)
    bodies = [world.add(wsim.PbdBody(mesh, name=name, **kw)) for name, mesh, kw in SPEC]
    world.step()
    assert bodies[1]._batch is not None
    v = bodies[1].state.v.numpy()
    v[3] = np.nan
    bodies[1].state.v.assign(v)
    with pytest.raises(wsim.SimulationDiverged, match="'b'"):
        world.step()


def test_block_moments_by_segment_equal_the_serial_sums():
    """The GPU path of the batch's momentum sums (``kernels.pbd.moments``: block reductions, one
    body per block thanks to the padding) run on the CPU with its block size: equal to the serial
    per-body sums the CPU path uses (which the tests above exercise)."""
    import warp as wp

    from wsim.kernels import pbd as kp

    world = wsim.World(fps=30.0, device="cpu", body_contact=False)
    bodies = [world.add(wsim.PbdBody(mesh, name=name, **kw)) for name, mesh, kw in SPEC]
    world.step()
    batch = bodies[0]._batch
    k = len(bodies)
    block = wp.zeros(k * batch._seg_stride, dtype=wp.float64, device="cpu")
    serial = wp.zeros_like(block)
    args = [batch.x, batch.v, batch.dxc, batch.inv_mass]
    wp.launch(kp.moments, dim=batch.model.n_particles, block_dim=kp.MOMENT_BLOCK, device="cpu",
              inputs=[*args, block, 0, batch._seg, batch._seg_first, batch._seg_stride])
    wp.launch(kp.moments_serial, dim=k, device="cpu",
              inputs=[*args, serial, 0, batch._seg_first, batch._seg_count, batch._seg_stride])
    b, s = block.numpy().reshape(k, -1)[:, :22], serial.numpy().reshape(k, -1)[:, :22]
    assert np.all(s[:, 0] > 0.0)  # every body's mass is summed
    np.testing.assert_allclose(b, s, rtol=1e-12, atol=1e-12 * np.abs(s).max())


def test_member_bounds_are_the_broad_phase_boxes(device):
    """The broad phase reads each batch member's surface box and fastest velocity component from
    one reduction on the device (``PbdBatch.member_bounds``): equal to the host's min, max and
    max |v| over the member's own particles (surface particles for the box; padding left out)."""
    w = wsim.World(fps=30.0, device=device, body_contact=True)
    w.add_collider(wsim.GroundPlane(friction=0.5))
    bodies = [w.add(wsim.PbdBody(mesh, dict(E=2e5, nu=0.3, rho=500.0), name=name, **kw)) for name, mesh, kw in SPEC]
    w.step()
    batch = bodies[0]._batch
    assert batch is not None and all(b._batch is batch for b in bodies)
    got = batch.member_bounds()
    for k, b in enumerate(bodies):
        x, v = b.particles()[: b.model.n_surface], b.velocities()
        np.testing.assert_array_equal(got[k, 0:3], x.min(axis=0))
        np.testing.assert_array_equal(got[k, 3:6], x.max(axis=0))
        assert got[k, 6] == np.abs(v).max()


def test_broad_phase_sweep_gives_the_all_pairs_test_pairs_in_order():
    """``candidate_pairs`` sweeps along x and tests y and z on the candidates only: the same pairs,
    in the same order (the order the projections run in), as testing every pair of swept boxes,
    on random boxes with many equal lower x bounds, margins, velocities and gravity."""
    from types import SimpleNamespace

    from wsim.pbd import contact

    rng = np.random.default_rng(7)
    dt = 1.0 / 60.0
    for trial in range(200):
        n = int(rng.integers(2, 30))
        lo = rng.random((n, 3)) * rng.choice([0.5, 3.0])
        if trial % 2:
            lo[:, 0] = np.round(lo[:, 0], 1)  # ties along the sweep axis
        hi = lo + rng.random((n, 3)) * 0.4
        v_max = rng.random(n) * rng.choice([0.0, 2.0])
        bodies = [SimpleNamespace(_gravity=(0.0, -9.81 * (trial % 3 > 0), 0.0), contact_margin=0.01 * (k % 2), _batch=None)
                  for k in range(n)]
        layout = contact._BroadPhase(bodies)
        layout.bounds = lambda _bodies, lo=lo, hi=hi, v=v_max: (lo.copy(), hi.copy(), v.copy())
        at = {id(b): k for k, b in enumerate(bodies)}
        got = [(at[id(a)], at[id(b)]) for a, b in contact.candidate_pairs(bodies, dt, {"broad_phase": layout})]
        g = np.array([np.linalg.norm(b._gravity) for b in bodies])
        grow = (v_max * dt + 0.5 * g * dt**2 + np.array([b.contact_margin for b in bodies]))[:, None]
        a_lo, a_hi = lo - grow, hi + grow
        overlap = np.all(a_hi[:, None, :] >= a_lo[None, :, :], axis=2) & np.all(a_hi[None, :, :] >= a_lo[:, None, :], axis=2)
        i, j = np.nonzero(np.triu(overlap, k=1))
        assert got == list(zip(i.tolist(), j.tolist())), trial
