"""The precomputed operator set of one BEM body (paper Sec. 3, Fig. 2 "precomputation").

For one (mesh, material, dt, options):

1. the Laplace-domain matrices at the CQ samples s_l = gamma(R zeta^l) / dt, l = 0..floor(L/2)
   (``wsim.bem.assembly``, Warp), row block by row block so device memory is never exceeded;
2. after each sample, the CQ weights of Eq. (15) folded into real H_k, G_k (k = 0..n_max) on the
   device (``cq_accumulate``); D_k, Q_k (3N x 3) on the host;
3. mass properties and A, C of Eq. (10) (``wsim.bem.mass``);
4. the LU factorization of H_0, H_0^-1, G' = G_0 + D_0 A + Q_0 C and H_0^-1 G' (float64;
   ``wsim.bem.factorization``: scipy LAPACK on the host, or cuSOLVER through CuPy on a GPU),
   used by the time stepping of Eq. (12).

Precision: every Laplace-domain sum and the CQ accumulation are float64; the stored H_k, G_k,
H_0^-1 and H_0^-1 G' are float32 (default, halves memory and bandwidth) or float64; the LU
factors, D_k, Q_k, A and C stay float64. The set is cached by content hash through
``wsim.cache``: a second build with the same inputs loads it instead.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.linalg
import warp as wp
from scipy.spatial import ConvexHull

from wsim import mesh as wmesh
from wsim.bem import cq
from wsim.bem.assembly import LaplaceAssembler
from wsim.bem.factorization import factorize
from wsim.bem.factorization import resolve as factorization_backend
from wsim.bem.mass import mass_properties, traction_maps
from wsim.bem.quadrature import Quadrature, quadrature_from
from wsim.bem.surface import BemSurface, prepare_surface
from wsim.cache import OperatorCache, content_key
from wsim.device import resolve_device
from wsim.errors import InvalidParameter
from wsim.kernels import bem_assembly as ka
from wsim.materials import ElasticMaterial
from wsim.validate import finite_number, positive_int

#: bump when the stored arrays or their meaning change
FORMAT_VERSION = 2
PRECISIONS = {"float32": np.float32, "float64": np.float64}


@dataclass(frozen=True)
class BemOperators:
    """Immutable operator set; N = number of collocation nodes (``surface.n_nodes``).

    Attributes:
        n_max: history length, n_max = floor(r_max / (c2 dt) + 2).
        H, G: (n_max + 1, 3N, 3N) time-domain matrices (H_0 includes the free term).
        D, Q: (n_max + 1, 3N, 3) fictitious-force matrices (float64).
        H0_lu: LU factors and pivots of H_0 (scipy.linalg.lu_factor layout, float64).
        H0_inv, H0_inv_Gp: H_0^-1 and H_0^-1 G' (3N, 3N).
        Gp: G' = G_0 + D_0 A + Q_0 C (3N, 3N, float64).
        A, C: (3, 3N) traction -> linear / angular acceleration maps of Eq. (10).
        mass [kg], com (3,) [m], inertia (3, 3) about com [kg m^2], volume [m^3].
    """

    surface: BemSurface
    material: ElasticMaterial
    dt: float
    method: str
    precision: str
    n_max: int
    r_max: float
    H: np.ndarray
    G: np.ndarray
    D: np.ndarray
    Q: np.ndarray
    H0_lu: tuple[np.ndarray, np.ndarray]
    H0_inv: np.ndarray
    H0_inv_Gp: np.ndarray
    Gp: np.ndarray
    A: np.ndarray
    C: np.ndarray
    mass: float
    com: np.ndarray
    inertia: np.ndarray
    volume: float
    key: str = ""
    timings: dict[str, float] = field(default_factory=dict, compare=False)

    @property
    def n_nodes(self) -> int:
        return self.surface.n_nodes

    @property
    def nbytes(self) -> int:
        """Bytes held by the matrices."""
        arrays = (self.H, self.G, self.D, self.Q, *self.H0_lu, self.H0_inv, self.H0_inv_Gp, self.Gp, self.A, self.C)
        return int(sum(a.nbytes for a in arrays))

    def solve_H0(self, b: np.ndarray) -> np.ndarray:
        """H_0^-1 b with the float64 LU factors."""
        return scipy.linalg.lu_solve(self.H0_lu, b)

    # -- cache (de)serialization -------------------------------------------------------------
    def to_arrays(self) -> dict[str, np.ndarray]:
        s = self.surface
        return {
            "nodes": s.nodes, "faces": s.faces, "vertex": s.vertex,
            "H": self.H, "G": self.G, "D": self.D, "Q": self.Q,
            "H0_lu_T": self.H0_lu[0].T, "H0_piv": self.H0_lu[1], "H0_inv": self.H0_inv, "H0_inv_Gp": self.H0_inv_Gp,
            "Gp": self.Gp, "A": self.A, "C": self.C, "com": self.com, "inertia": self.inertia,
            "scalars": np.array([self.mass, self.volume, self.r_max, self.dt, self.n_max], dtype=np.float64),
        }


def _from_arrays(a: dict[str, np.ndarray], surface: BemSurface, material: ElasticMaterial, method: str,
                 precision: str, key: str) -> BemOperators:
    mass, volume, r_max, dt, n_max = a["scalars"].tolist()
    return BemOperators(
        surface=surface, material=material, dt=dt, method=method, precision=precision, n_max=int(n_max), r_max=r_max,
        H=a["H"], G=a["G"], D=a["D"], Q=a["Q"], H0_lu=(a["H0_lu_T"].T, a["H0_piv"]), H0_inv=a["H0_inv"],
        H0_inv_Gp=a["H0_inv_Gp"], Gp=a["Gp"], A=a["A"], C=a["C"], mass=mass, com=a["com"], inertia=a["inertia"],
        volume=volume, key=key,
    )


def surface_diameter(points: np.ndarray) -> float:
    """r_max: the largest distance between two points of the surface (attained at hull vertices)."""
    p = np.asarray(points, dtype=np.float64)
    try:
        p = p[ConvexHull(p).vertices]
    except Exception:  # degenerate hull (cannot happen for a valid closed mesh): use every point
        pass
    best = 0.0
    for start in range(0, len(p), 1024):
        d = np.linalg.norm(p[start : start + 1024, None, :] - p[None, :, :], axis=-1)
        best = max(best, float(d.max()))
    return best


def assembly_devices(device: Any = None, devices: Any = None) -> list[wp.Device]:
    """The devices a build spreads its row blocks over: ``devices`` = None (``device`` alone),
    "all" (every CUDA device; the CPU without one) or a list (a device may repeat: its blocks then
    take turns on it, which is how the CPU tests the path)."""
    if devices is None:
        return [resolve_device(device)]
    if isinstance(devices, str) and devices == "all":
        cuda = wp.get_cuda_devices()
        return list(cuda) if cuda else [resolve_device("cpu")]
    if isinstance(devices, str) or not isinstance(devices, (list, tuple)) or not devices:
        raise InvalidParameter(f"devices = {devices!r}: None, 'all' or a non-empty list of devices (e.g. ['cuda:0', 'cuda:1'])")
    return [resolve_device(d) for d in devices]


def _fault_in(arrays: list[np.ndarray]) -> None:
    """Touch one element of every 4 KB page (numpy's scalar fill releases the GIL), so the
    kernel maps the memory now rather than in the device -> host copies."""
    for a in arrays:
        a.reshape(-1)[:: max(1, 4096 // a.itemsize)] = 0


def _rows_per_block(device: wp.Device, n: int, n_max: int, memory_limit: int | None) -> int:
    """Rows whose complex H, G and n_max + 1 real accumulators of each fit the budget."""
    per_row = 3 * 3 * n * (8 * (4 + 2 * (n_max + 1)) + 4 * (n_max + 1)) + 5 * 9 * 8  # + the float32 cast
    if memory_limit is None:
        memory_limit = int(0.6 * device.free_memory) if device.is_cuda else 2 << 30
    rows = max(1, int(memory_limit // per_row))
    return min(n, rows)


def build_operators(
    mesh: Any,
    material: ElasticMaterial,
    dt: float,
    *,
    method: str = "bdf1",
    eps: float = 1e-10,
    precision: str = "float32",
    double_nodes: float | None = None,
    n_max: int | None = None,
    device: Any = None,
    cache: bool | OperatorCache = True,
    memory_limit: int | None = None,
    progress: bool | None = None,
    factorization: str = "auto",
    devices: Any = None,
    **quadrature: Any,
) -> BemOperators:
    """Build (or load from the cache) the operator set of one BEM body.

    Args:
        mesh: a ``trimesh.Trimesh`` or (vertices, faces); closed and outward-oriented.
        material: the elastic material (``incompressible=True`` for nu = 0.5).
        dt: time step [s] (> 0).
        method: CQ multistep method, "bdf1" (paper) or "bdf2".
        eps: CQ accuracy parameter (R = eps^(1 / (2 n_max))).
        precision: storage of H_k, G_k, H_0^-1, H_0^-1 G': "float32" or "float64".
        double_nodes: crease angle [deg] for double nodes at sharp edges, or None.
        n_max: override the history length (default floor(r_max / (c2 dt) + 2)).
        device: Warp device for the assembly (default: CUDA if present).
        cache: True (default folder), False, or an ``OperatorCache``.
        memory_limit: device bytes the row blocks may use (default 60 % of free GPU memory, 2 GiB on CPU).
        progress: a progress bar over (row block, sample): ``wsim.progress.show_progress`` (None:
            when stderr is a terminal; ``WSIM_PROGRESS=0`` hides it whatever is asked).
        factorization: where the LU of H_0 and the products H_0^-1, H_0^-1 G' run: "scipy" (host),
            "cupy" (GPU, the optional ``gpu`` extra) or "auto" (CuPy on a CUDA build when it
            imports); ``wsim.bem.factorization``. Not part of the cache key (same factors to round-off).
        devices: spread the Laplace-domain assembly and CQ accumulation over several devices by row
            blocks: "all" (every CUDA device) or a list, e.g. ["cuda:0", "cuda:1"]; the blocks are
            launched on all of them before any is read back, so they run together. The factorization
            runs on the first. The same operators as on one device (each block is computed alike).
            Not part of the cache key.
        **quadrature: :class:`~wsim.bem.quadrature.Quadrature` knobs.
    """
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    if not isinstance(material, ElasticMaterial):
        raise InvalidParameter(f"material must be an ElasticMaterial, got {type(material).__name__}")
    dt = finite_number(dt, "dt")
    if dt <= 0.0:
        raise InvalidParameter(f"dt = {dt} s must be > 0")
    if precision not in PRECISIONS:
        raise InvalidParameter(f"precision = {precision!r} must be one of {', '.join(PRECISIONS)}")
    if method not in cq.GAMMA:
        raise InvalidParameter(f"CQ method = {method!r} must be one of {', '.join(cq.GAMMA)}")
    if not (0.0 < eps < 1.0):
        raise InvalidParameter(f"eps = {eps!r} must be in (0, 1)")
    factorization_backend(factorization, False)  # a bad name fails before any work
    assembly_devices(device, devices)  # and a bad device list
    quad = quadrature_from(quadrature)
    vertices, faces = wmesh.surface_arrays(mesh, "bem mesh")
    surface = prepare_surface(vertices, faces, double_nodes=double_nodes, name="bem mesh")
    r_max = surface_diameter(surface.nodes)
    if n_max is None:
        n_max = cq.n_max_for(r_max, material.c2, dt)
    else:
        n_max = positive_int(n_max, "n_max")
    timings["surface"] = time.perf_counter() - t_start

    def build() -> dict[str, np.ndarray]:
        t_build = time.perf_counter()
        out = _build(surface, material, dt, method, eps, precision, int(n_max), r_max, quad, device,
                     memory_limit, progress, timings, factorization, devices).to_arrays()
        timings["build"] = time.perf_counter() - t_build
        return out

    params = {"material": material.as_key(), "dt": dt, "method": method, "eps": eps, "precision": precision,
              "double_nodes": double_nodes, "n_max": int(n_max), "quadrature": quad.as_key()}
    arrays = {"nodes": surface.nodes, "faces": surface.faces, "vertex": surface.vertex}
    key = content_key("bem_operators", arrays=arrays, params=params, version=FORMAT_VERSION)
    if cache is False:
        result = build()
    else:
        store = cache if isinstance(cache, OperatorCache) else OperatorCache()
        t0 = time.perf_counter()
        result = store.get_or_build("bem_operators", arrays=arrays, params=params, version=FORMAT_VERSION,
                                    build=build, meta={"n_nodes": surface.n_nodes, "n_max": int(n_max)})
        # a miss builds and then stores; a hit only loads (and verifies the checksums)
        timings["cache_store" if "build" in timings else "cache_load"] = (
            time.perf_counter() - t0 - timings.get("build", 0.0))
    ops = _from_arrays(result, surface, material, method, precision, key)
    timings["total"] = time.perf_counter() - t_start
    ops.timings.update(timings)
    return ops


def _build(surface: BemSurface, material: ElasticMaterial, dt: float, method: str, eps: float, precision: str,
           n_max: int, r_max: float, quad: Quadrature, device: Any, memory_limit: int | None, progress: bool | None,
           timings: dict[str, float], factorization: str = "auto", devices: Any = None) -> BemOperators:
    from tqdm.auto import tqdm

    from wsim.progress import show_progress

    t0 = time.perf_counter()
    # one assembler a device; the row blocks go to them in turn (``assembly_devices``)
    assemblers = [LaplaceAssembler(surface, material, quad, d) for d in assembly_devices(device, devices)]
    dev = assemblers[0].device  # the factorization's and the host buffers' device
    props = mass_properties(surface.nodes, surface.faces, material.rho)
    A, C = traction_maps(surface, props)
    s_l, R, L = cq.sample_points(dt, n_max, method, eps)
    W = cq.half_weights(R, L, n_max)  # (half, n_max + 1)
    n = surface.n_nodes
    dtype = PRECISIONS[precision]
    wp_dtype = wp.float32 if dtype == np.float32 else wp.float64
    D = np.zeros((n_max + 1, 3 * n, 3))
    Q = np.zeros_like(D)
    cols = 3 * n
    # the float64 H_0, G_0 wait where the factorization runs: on its GPU they never cross to the
    # host and back (the bunny: 1.75 GB of host buffers, a copy each way and the fold on the
    # host, ~1.5 s of its build on an H100). Allocated before the row blocks are sized, so the
    # blocks' share of the free memory leaves them out.
    backend = factorization_backend(factorization, dev.is_cuda)
    if backend == "cupy":
        H0_buf, G0_buf = (wp.empty((cols, cols), dtype=wp.float64, device=dev) for _ in range(2))
    else:
        H0_buf, G0_buf = np.empty((cols, cols)), np.empty((cols, cols))
    # 2-D (Warp's strides are 32 bits: a 3-D stack of 10k-node matrices would overflow them)
    H_host = np.empty(((n_max + 1) * cols, cols), dtype=dtype)
    G_host = np.empty_like(H_host)
    # Host results in pageable memory whose pages a thread faults in while the devices assemble.
    # Page-locked buffers (cudaHostAlloc) took 1.8-3.6 s to allocate for the bunny's 5.2 GB on H100
    # hosts, before the assembly could start and holding up the devices' own allocations; faulting
    # in numpy's (transparent huge pages) took 0.56 s, and the copies into them 0.30 s instead of
    # 0.10 s (tools/results/bench_bem_precompute_bunny_host_buffers_h100.jsonl). On several GPUs
    # the pageable copies no longer overlap across the devices (the bunny's: 0.5 s on one).
    host_buffers = [H_host, G_host] + ([H0_buf, G0_buf] if backend != "cupy" else [])
    fault_in = threading.Thread(target=_fault_in, args=(host_buffers,), daemon=True)
    if any(a.device.is_cuda for a in assemblers):
        fault_in.start()
    # a device named twice shares its memory between its two sets of buffers
    shares = Counter(a.device.alias for a in assemblers)
    rows = max(1, min(_rows_per_block(a.device, n, n_max, memory_limit) // shares[a.device.alias] for a in assemblers))
    # a multiple of the device count of blocks, so no device idles in the last batch, and at least
    # one block each: on two H200s all 3485 rows of the bunny fitted one block, and the first
    # measurement gave 4.24 s of assembly on one GPU and on "two"
    k = len(assemblers)
    n_blocks = -(-n // rows)  # the blocks the memory needs,
    n_blocks = -(-n_blocks // k) * k  # rounded up to a multiple of the devices
    rows = -(-n // n_blocks)
    blocks = [(r0, min(rows, n - r0)) for r0 in range(0, n, rows)]
    # Warp views of the host buffers, the copies' destinations
    H_wp, G_wp = (wp.array(a, dtype=wp_dtype, device="cpu", copy=False) for a in (H_host, G_host))
    H0_wp, G0_wp = (b if backend == "cupy" else wp.array(b, dtype=wp.float64, device="cpu", copy=False)
                    for b in (H0_buf, G0_buf))
    timings["setup"] = time.perf_counter() - t0
    t_assembly = t_transfer = 0.0
    bar = tqdm(total=len(blocks) * len(s_l), desc="BEM operators", unit="sample", disable=not show_progress(progress))
    work = []  # per device: its assembler, row block buffers and accumulators (H_k: rows k 3 rows ..)
    weights = {}  # the CQ weights of each sample, real and imaginary, on each device (uploaded once)
    for a in assemblers:
        acc_H = wp.zeros(((n_max + 1) * 3 * rows, cols), dtype=wp.float64, device=a.device)
        work.append((a, a.block(rows), acc_H, wp.zeros_like(acc_H),
                     wp.empty(acc_H.shape, dtype=wp.float32, device=a.device) if wp_dtype == wp.float32 else None))
        weights[a.device.alias] = [tuple(wp.array(np.ascontiguousarray(part), dtype=wp.float64, device=a.device)
                                         for part in (w.real, w.imag)) for w in W]
    for first in range(0, len(blocks), len(work)):
        # one block a device at a time, all launched before any is read: the devices run together
        batch = list(zip(work, blocks[first:first + len(work)]))
        t1 = time.perf_counter()
        for (a, block, acc_H, acc_G, _), _ in batch:
            acc_H.zero_()
            acc_G.zero_()
        for l, s in enumerate(s_l):
            for (a, block, acc_H, acc_G, _), (r0, nr) in batch:
                a.assemble(complex(s), r0, nr, block)
                w_re, w_im = weights[a.device.alias][l]
                wp.launch(ka.cq_accumulate, dim=(3 * nr, cols), inputs=[block.H_re, block.H_im, w_re, w_im, acc_H],
                          device=a.device)
                wp.launch(ka.cq_accumulate, dim=(3 * nr, cols), inputs=[block.G_re, block.G_im, w_re, w_im, acc_G],
                          device=a.device)
            for (a, block, *_), (r0, nr) in batch:
                small = a.small_to_host(block, r0, nr, props.com)
                sl = slice(3 * r0, 3 * (r0 + nr))
                D[:, sl] += np.real(W[l][:, None, None] * small["D"][None])
                Q[:, sl] += np.real(W[l][:, None, None] * small["Q"][None])
                bar.update(1)
        for (a, *_), _ in batch:
            wp.synchronize_device(a.device)
        t2 = time.perf_counter()
        if fault_in.is_alive():
            fault_in.join()
        for (a, block, acc_H, acc_G, cast), (r0, nr) in batch:
            count = 3 * nr * cols
            for acc, host, host0 in ((acc_H, H_wp, H0_wp), (acc_G, G_wp, G0_wp)):
                wp.copy(host0, acc, dest_offset=3 * r0 * cols, src_offset=0, count=count)
                src = acc
                if cast is not None:
                    wp.launch(ka.to_float32, dim=acc.shape, inputs=[acc, cast], device=a.device)
                    src = cast
                for k in range(n_max + 1):
                    wp.copy(host, src, dest_offset=k * cols * cols + 3 * r0 * cols, src_offset=k * 3 * rows * cols, count=count)
        for (a, *_), _ in batch:
            wp.synchronize_device(a.device)
        t_transfer += time.perf_counter() - t2
        t_assembly += t2 - t1
    H, G = (a.reshape(n_max + 1, cols, cols) for a in (H_host, G_host))
    bar.close()
    # the row blocks' device buffers (the loops' names too): the factorization needs the room
    del work, batch, block, acc_H, acc_G, acc, src, cast, host, host0
    timings["assembly"] = t_assembly
    timings["transfer"] = t_transfer
    t3 = time.perf_counter()
    # G' = G_0 + D_0 A + Q_0 C is folded where G_0 lies. H_0, G_0 are handed over with their only
    # references: on the GPU factorize frees each once its Fortran-ordered copy is made (the
    # factorization's peak stays ~3.5 (3N)^2 float64, ~26 GB at N = 10088)
    buffers = [H0_buf, G0_buf]
    del H_wp, G_wp, H0_wp, G0_wp, H0_buf, G0_buf
    if dev.is_cuda:
        wp.synchronize_device(dev)  # the row blocks' freed memory goes back to the driver, for CuPy
    f = factorize(buffers.pop(0), buffers.pop(0), backend, dev.ordinal if dev.is_cuda else 0, dtype,
                  frame_terms=(D[0], Q[0], A, C))
    timings["factorization"] = time.perf_counter() - t3
    return BemOperators(
        surface=surface, material=material, dt=dt, method=method, precision=precision, n_max=n_max, r_max=r_max,
        H=H, G=G, D=D, Q=Q, H0_lu=f.lu, H0_inv=f.H0_inv, H0_inv_Gp=f.H0_inv_Gp, Gp=f.Gp,
        A=A, C=C, mass=props.mass, com=props.com, inertia=props.inertia, volume=props.volume,
    )
