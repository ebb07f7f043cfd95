"""Recorded launches (``wsim.launch.Launcher``) launch exactly what ``wp.launch`` would, whatever changed."""

from __future__ import annotations

import numpy as np
import warp as wp

from wsim.launch import Launcher


@wp.struct
class Frame:
    scale: wp.float64
    shift: wp.array(dtype=wp.float64)


@wp.kernel
def affine(x: wp.array(dtype=wp.vec3d), frame: Frame, M: wp.mat33d, c: wp.vec3d, k: int, s: wp.float64,
           out: wp.array(dtype=wp.vec3d)):
    i = wp.tid()
    out[i] = frame.scale * (M * x[i]) + c * wp.float64(k) + wp.vec3d(s, frame.shift[0], wp.float64(0.0))


def test_replayed_launch_follows_every_kind_of_change(device, rng):
    launch = Launcher(wp.get_device(device))
    xs = [wp.array(rng.standard_normal((n, 3)), dtype=wp.vec3d, device=device) for n in (7, 7, 5)]
    frame = Frame()
    frame.scale = wp.float64(2.0)
    frame.shift = wp.array([0.5], dtype=wp.float64, device=device)
    out = wp.zeros(7, dtype=wp.vec3d, device=device)
    M = rng.standard_normal((3, 3))
    # each call changes one thing: nothing, an array, a matrix, a vector, an int, a scalar, a struct
    # field (set in place), a struct's array field, the launch size, a reshaped view of the same memory
    calls = [(xs[0], M, (1.0, 2.0, 3.0), 1, 0.0, None), (xs[0], M, (1.0, 2.0, 3.0), 1, 0.0, None),
             (xs[1], M, (1.0, 2.0, 3.0), 1, 0.0, None), (xs[1], 2.0 * M, (1.0, 2.0, 3.0), 1, 0.0, None),
             (xs[1], 2.0 * M, (0.0, 2.0, 3.0), 1, 0.0, None), (xs[1], 2.0 * M, (0.0, 2.0, 3.0), 3, 0.0, None),
             (xs[1], 2.0 * M, (0.0, 2.0, 3.0), 3, -1.5, None), (xs[1], 2.0 * M, (0.0, 2.0, 3.0), 3, -1.5, "scale"),
             (xs[1], 2.0 * M, (0.0, 2.0, 3.0), 3, -1.5, "shift"), (xs[2], 2.0 * M, (0.0, 2.0, 3.0), 3, -1.5, None),
             (xs[1].reshape((7,)), 2.0 * M, (0.0, 2.0, 3.0), 3, -1.5, None)]
    for x, A, c, k, s, field in calls:
        if field == "scale":
            frame.scale = wp.float64(-0.25)
        elif field == "shift":
            frame.shift = wp.array([4.0], dtype=wp.float64, device=device)
        args = [x, frame, wp.mat33d(*A.ravel()), wp.vec3d(*c), k, wp.float64(s)]
        out.zero_()
        launch(affine, x.shape[0], [*args, out])
        got = out.numpy()
        out.zero_()
        wp.launch(affine, dim=x.shape[0], inputs=[*args, out], device=device)
        np.testing.assert_array_equal(got, out.numpy())
        xn = x.numpy()
        expect = float(frame.scale.value if hasattr(frame.scale, "value") else frame.scale) * xn @ A.T
        expect += k * np.asarray(c) + np.array([s, frame.shift.numpy()[0], 0.0])
        np.testing.assert_allclose(got[: len(xn)], expect, rtol=1e-14, atol=1e-14)


def test_copy_matches_the_source(device, rng):
    launch = Launcher(wp.get_device(device))
    for dtype, shape in ((wp.float64, (9,)), (wp.vec3d, (9, 3))):
        dst = wp.zeros(9, dtype=dtype, device=device)
        for _ in range(2):  # the same call site, a new source
            src = wp.array(rng.standard_normal(shape), dtype=dtype, device=device)
            launch.copy(dst, src)
            np.testing.assert_array_equal(dst.numpy(), src.numpy())


@wp.kernel
def reciprocal(s: wp.float64, out: wp.array(dtype=wp.float64)):
    i = wp.tid()
    out[i] = wp.float64(1.0) / s


def test_replay_tells_negative_zero_and_takes_numpy_sizes():
    """-0.0 == 0.0, but a kernel tells them apart (1 / s): a replay re-packs it. A NumPy integer
    launch size is a size like any other."""
    launch = Launcher(wp.get_device("cpu"))
    out = wp.zeros(3, dtype=wp.float64, device="cpu")
    for s in (0.0, -0.0, wp.float64(0.0), wp.float64(-0.0)):
        launch(reciprocal, np.int64(3), [s if isinstance(s, float) else s, out])
        assert np.all(out.numpy() == (np.inf if np.copysign(1.0, float(getattr(s, "value", s))) > 0 else -np.inf))
