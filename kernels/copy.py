"""Array copies as kernels, so a step's copies replay like its other launches (``wsim.launch``)."""

from __future__ import annotations

import warp as wp


@wp.kernel
def copy_float64(src: wp.array(dtype=wp.float64), dst: wp.array(dtype=wp.float64)):
    """dst = src (same length)."""
    i = wp.tid()
    dst[i] = src[i]


@wp.kernel
def copy_vec3d(src: wp.array(dtype=wp.vec3d), dst: wp.array(dtype=wp.vec3d)):
    """dst = src (same length)."""
    i = wp.tid()
    dst[i] = src[i]
