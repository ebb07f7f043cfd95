"""Point evaluation of the Warp BEM kernels (``kernels/bem_kernels.py``), for tests and studies."""

from __future__ import annotations

import numpy as np
import warp as wp

from wsim.bem.fundamental import inverse_speeds
from wsim.device import resolve_device
from wsim.kernels import bem_kernels as kb


def evaluate_kernels(x, y, n, s: complex, material, x_bar, device=None) -> dict[str, np.ndarray]:
    """u, p, d, q (each (K, 3, 3) complex128) at point pairs x -> y with normals n at y."""
    dev = resolve_device(device)
    a1, a2 = inverse_speeds(material)
    k = len(x)
    with wp.ScopedDevice(dev):
        arrays = [wp.array(np.asarray(v, dtype=np.float64), dtype=wp.vec3d) for v in (x, y, n)]
        re = wp.zeros((4, k), dtype=wp.mat33d)
        im = wp.zeros((4, k), dtype=wp.mat33d)
        wp.launch(
            kb.evaluate_kernels,
            dim=k,
            inputs=[*arrays, wp.vec2d(s.real, s.imag), wp.float64(a1), wp.float64(a2), wp.float64(material.rho),
                    wp.vec3d(*np.asarray(x_bar, dtype=np.float64)), re, im],
        )
        out = re.numpy() + 1j * im.numpy()
    return dict(zip("upd" "q", out))
