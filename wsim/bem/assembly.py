"""Laplace-domain BEM matrices H(s), G(s), D(s), Q(s) assembled by Warp (``kernels/bem_assembly.py``).

Row i of the collocation equations at node x_i (paper Eq. 8 before the CQ weights):

    H(s) u = G(s) p + D(s) (a - g') + Q(s) alpha,      H (3N, 3N) includes the free term c(x_i),

with D, Q (3N, 3) from the body-force kernels (19)-(21): Q = L + D [x_i - x_bar]x^T per row.
Matrices are row-major with interleaved components (row 3 i + a, column 3 v + b); all values
are float64 (real and imaginary parts in separate arrays on the device).

On CUDA the triangles are coloured so that no two triangles of one launch share a node (H and G
blocks are then written without races and in a fixed order); a CPU launch is serial and does
all triangles in one pass.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from wsim.bem.fundamental import inverse_speeds
from wsim.rigid import cross_matrix
from wsim.bem.mass import mass_properties
from wsim.bem.quadrature import Quadrature, quadrature_from
from wsim.bem.surface import BemSurface, free_term, prepare_surface
from wsim.device import resolve_device
from wsim.errors import InvalidParameter
from wsim.kernels import bem_assembly as ka
from wsim.materials import ElasticMaterial
from wsim.colouring import colour_constraints

#: triangles per thread on CUDA (one thread: one row, a chunk of one colour's triangles)
CUDA_CHUNK = 8


def kappa_of(material: ElasticMaterial) -> float:
    """mu / (lambda + 2 mu) = (c2 / c1)^2; 0 in the incompressible limit."""
    a1, a2 = inverse_speeds(material)
    return (a1 / a2) ** 2


@dataclass
class RowBlock:
    """Device arrays of one row block [row0, row0 + rows) at one s (real and imaginary parts)."""

    H_re: wp.array
    H_im: wp.array
    G_re: wp.array
    G_im: wp.array
    D_re: wp.array
    D_im: wp.array
    L_re: wp.array
    L_im: wp.array
    S: wp.array

    def zero(self) -> None:
        for a in (self.H_re, self.H_im, self.G_re, self.G_im, self.D_re, self.D_im, self.L_re, self.L_im, self.S):
            a.zero_()


class LaplaceAssembler:
    """Uploads one surface and its quadrature rules once; assembles row blocks at any s."""

    def __init__(self, surface: BemSurface, material: ElasticMaterial, quadrature: Quadrature, device=None) -> None:
        self.surface = surface
        self.material = material
        self.quadrature = quadrature
        self.device = resolve_device(device)
        self.a1, self.a2 = inverse_speeds(material)
        self.kappa = kappa_of(material)
        n = surface.n_nodes
        m = surface.faces.shape[0]
        if self.device.is_cuda:
            order, offsets = colour_constraints(surface.faces, n)
            self.ranges = [(int(offsets[c]), int(offsets[c + 1])) for c in range(len(offsets) - 1)]
            self.chunk = CUDA_CHUNK
        else:
            order, self.ranges, self.chunk = np.arange(m), [(0, m)], max(m, 1)
        reg_b, reg_w, reg_off = quadrature.regular_rules()
        sing_b, sing_w = quadrature.singular_rule()
        # where a vertex has several nodes, c(x) is split off the principal value (surface docstring)
        first = surface.first_node()
        c_own = np.zeros((n, 3, 3))
        shared = np.flatnonzero(np.bincount(surface.vertex)[surface.vertex] > 1)
        if shared.size:
            c_own[shared] = free_term(surface, shared, self.kappa)
        with wp.ScopedDevice(self.device):
            vec3 = lambda a: wp.array(np.ascontiguousarray(a, dtype=np.float64), dtype=wp.vec3d)  # noqa: E731
            f64 = lambda a: wp.array(np.ascontiguousarray(a, dtype=np.float64), dtype=wp.float64)  # noqa: E731
            self.x = vec3(surface.nodes)
            self.group = wp.array(surface.vertex.astype(np.int32), dtype=wp.int32)
            self.tri = wp.array(surface.faces.astype(np.int32), dtype=wp.vec3i)
            self.tri_order = wp.array(np.asarray(order, dtype=np.int32), dtype=wp.int32)
            self.normals = vec3(surface.normals)
            self.areas = f64(surface.areas)
            self.h = f64(surface.longest_edge)
            self.reg_b, self.reg_w = vec3(reg_b), f64(reg_w)
            self.reg_off = wp.array(reg_off, dtype=wp.int32)
            self.sing_b, self.sing_w = vec3(sing_b), f64(sing_w)
            self.first = wp.array(first, dtype=wp.int32)
            self.c_own = wp.array(c_own, dtype=wp.mat33d)

    @property
    def n(self) -> int:
        return self.surface.n_nodes

    def block(self, rows: int) -> RowBlock:
        """Allocate the device arrays for ``rows`` collocation nodes."""
        cols = 3 * self.n
        with wp.ScopedDevice(self.device):
            mats = [wp.zeros((3 * rows, cols), dtype=wp.float64) for _ in range(4)]
            small = [wp.zeros(rows, dtype=wp.mat33d) for _ in range(5)]
        return RowBlock(*mats, *small)

    def assemble(self, s: complex, row0: int, rows: int, out: RowBlock) -> None:
        """H, G, D, L for nodes row0 .. row0 + rows - 1 at frequency s into ``out`` (zeroed here)."""
        if not np.isfinite(s) or s.real <= 0.0:
            raise InvalidParameter(f"Laplace frequency s = {s} must have a positive real part")
        out.zero()
        q = self.quadrature
        common = [self.x, self.group, self.tri, self.tri_order, self.normals, self.areas, self.h,
                  self.reg_b, self.reg_w, self.reg_off, q.near_levels, wp.float64(q.near_ratio),
                  self.sing_b, self.sing_w, wp.vec2d(s.real, s.imag), wp.float64(self.a1), wp.float64(self.a2),
                  wp.float64(self.material.rho), wp.float64(self.kappa),
                  out.H_re, out.H_im, out.G_re, out.G_im, out.D_re, out.D_im, out.L_re, out.L_im, out.S]
        with wp.ScopedDevice(self.device):
            for begin, end in self.ranges:
                chunks = -(-(end - begin) // self.chunk)
                wp.launch(ka.assemble_rows, dim=(rows, chunks), inputs=[row0, self.chunk, begin, end, *common])
            wp.launch(ka.add_diagonal, dim=(rows, 3, 3), inputs=[row0, self.first, self.c_own, out.S, out.H_re])

    def small_to_host(self, out: RowBlock, row0: int, rows: int, com: np.ndarray) -> dict[str, np.ndarray]:
        """Complex D and Q (3 rows, 3) of a row block; Q = L + D [x_i - com]x^T (Eq. 20)."""
        D = out.D_re.numpy()[:rows] + 1j * out.D_im.numpy()[:rows]
        L = out.L_re.numpy()[:rows] + 1j * out.L_im.numpy()[:rows]
        lever = cross_matrix(self.surface.nodes[row0 : row0 + rows] - com)
        Q = L + D @ np.swapaxes(lever, -1, -2)
        return {"D": D.reshape(3 * rows, 3), "Q": Q.reshape(3 * rows, 3)}

    def to_host(self, out: RowBlock, row0: int, rows: int, com: np.ndarray) -> dict[str, np.ndarray]:
        """Complex H, G (3 rows, 3N), D and Q (3 rows, 3) of a row block."""
        r = 3 * rows
        H = out.H_re.numpy()[:r] + 1j * out.H_im.numpy()[:r]
        G = out.G_re.numpy()[:r] + 1j * out.G_im.numpy()[:r]
        return {"H": H, "G": G, **self.small_to_host(out, row0, rows, com)}


@dataclass(frozen=True)
class LaplaceOperators:
    """H, G (3N, 3N) and D, Q (3N, 3) complex at one s, with the surface they were built on."""

    s: complex
    H: np.ndarray
    G: np.ndarray
    D: np.ndarray
    Q: np.ndarray
    surface: BemSurface
    com: np.ndarray


def laplace_operators(vertices, faces, material: ElasticMaterial, s: complex, *, double_nodes: float | None = None,
                      device=None, **quadrature) -> LaplaceOperators:
    """All four Laplace-domain matrices at one complex frequency s (Re s > 0), in one assembly.

    The mesh is validated (closed, outward, no degenerate faces) before anything is assembled.
    ``quadrature`` takes the :class:`~wsim.bem.quadrature.Quadrature` knobs.
    """
    if not isinstance(material, ElasticMaterial):
        raise InvalidParameter(f"material must be an ElasticMaterial, got {type(material).__name__}")
    surface = prepare_surface(vertices, faces, double_nodes=double_nodes)
    quad = quadrature_from(quadrature)
    s = complex(s)
    assembler = LaplaceAssembler(surface, material, quad, device)
    n = surface.n_nodes
    block = assembler.block(n)
    assembler.assemble(s, 0, n, block)
    com = mass_properties(surface.nodes, surface.faces, material.rho).com
    host = assembler.to_host(block, 0, n, com)
    return LaplaceOperators(s=s, surface=surface, com=com, **host)


def laplace_matrices(vertices, faces, material: ElasticMaterial, s: complex, **options) -> tuple[np.ndarray, np.ndarray]:
    """(H_hat, G_hat): complex (3N, 3N) at frequency s, free term included in H_hat (paper Eq. 8).

    Options: ``double_nodes``, ``device`` and the quadrature knobs (see :func:`laplace_operators`).
    """
    ops = laplace_operators(vertices, faces, material, s, **options)
    return ops.H, ops.G
