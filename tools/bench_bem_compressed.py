"""The compressed BEM history on a GPU against the dense one (issue 20): time per history pass,
bytes of the matrices, and the error of the compressed history on smooth ring vectors.

    python tools/bench_bem_compressed.py --device cuda:0 [--divisions 22] [--ratios 8,32] [--reps 200]

The body is the paper's bumpy cube (jelly, dt 0.01; divisions 22: N = 2906, n_max 5). Dense: the
``history_matvec`` kernel over H_k, G_k (float32, 2 n_max matrices). Compressed
(``kernels/bem_compressed.py``): the two new ring vectors transformed (a float64 prefix scan and
the coefficients), the kept coefficients of all 2 n_max matrices summed against the transformed
rings (float32 values, uint16 columns) and one inverse transform. One JSON line per case.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import warp as wp

import wsim
from wsim import mesh as wmesh
from wsim.bem import build_operators, stepper
from wsim.bem.compression import (_from_coefficients, node_order, pack_rows, permutation, smooth_fields,
                                  transform)
from wsim.device import quiet_warp
from wsim.kernels import bem_compressed as kc


def timed(fn, reps: int, device) -> float:
    fn()
    wp.synchronize_device(device)
    t = time.perf_counter()
    for _ in range(reps):
        fn()
    wp.synchronize_device(device)
    return (time.perf_counter() - t) / reps


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default=None)
    ap.add_argument("--divisions", type=int, default=22)
    ap.add_argument("--ratios", default="8,32")
    ap.add_argument("--reps", type=int, default=200)
    args = ap.parse_args()
    quiet_warp()
    device = wp.get_device(args.device)
    cube = wmesh.bumpy_cube(size=0.45, divisions=args.divisions, amplitude=0.04)
    jelly = wsim.ElasticMaterial(mu=5e5, nu=0.5, rho=1e3, incompressible=True)
    t = time.perf_counter()
    ops = build_operators(cube, jelly, 0.01, device=device, cache=False)
    build_s = time.perf_counter() - t
    n_max, n = ops.n_max, 3 * ops.n_nodes
    step = 7

    # dense history on the device, smooth rings
    so = stepper.step_operators(ops, device, "warp" if device.is_cuda else "blas")
    U = smooth_fields(ops.surface.nodes, n_max, seed=1).T
    P = smooth_fields(ops.surface.nodes, n_max, seed=2).T * 1e3
    Ud, Pd = so.vectors(n_max), so.vectors(n_max)
    Ud.assign(np.pad(U, ((0, 0), (0, so.pitch - n))).astype(np.float32))
    Pd.assign(np.pad(P, ((0, 0), (0, so.pitch - n))).astype(np.float32))
    B = wp.zeros((n_max, 6), dtype=so.dtype, device=device)
    h = so.vectors()
    view = stepper.vec4_view if so.backend == "warp" else (lambda a: a)
    dense_s = timed(lambda: stepper.history(so, view(Ud), view(Pd), B, step, h), args.reps, device)
    h_dense = h.numpy()[:n].astype(np.float64)
    dense_bytes = int(so.H.capacity + so.G.capacity)
    print(json.dumps({"case": "dense", "device": device.name, "N": ops.n_nodes, "n_max": n_max, "build_s": round(build_s, 2),
                      "history_ms": 1e3 * dense_s, "matrix_bytes": dense_bytes,
                      "GBps": dense_bytes / dense_s / 1e9}), flush=True)

    # compressed: coefficients once per matrix, every ratio from them
    s = ops.surface
    perm = permutation(s.n_nodes, "v+c", node_order(s.nodes, s.faces, s.vertex))
    ratios = [float(r) for r in args.ratios.split(",")]
    kept: dict[float, list] = {r: [] for r in ratios}
    t = time.perf_counter()
    for A in [*ops.H[1:], *ops.G[1:]]:
        coeffs = transform(np.asarray(A, dtype=np.float64), perm)
        norm = float(np.linalg.norm(A))
        for r in ratios:
            kept[r].append(_from_coefficients(coeffs, n, perm, int(round(n * n / r)), norm))
        del coeffs
    compress_s = time.perf_counter() - t
    size = kept[ratios[0]][0].size

    def rows_of(X: np.ndarray) -> np.ndarray:
        out = np.zeros((len(X), size))
        out[:, :n] = X[:, perm]
        return out

    flat_u = wp.array(rows_of(U).ravel(), dtype=wp.float64, device=device)
    flat_p = wp.array(rows_of(P).ravel(), dtype=wp.float64, device=device)
    S = wp.empty_like(flat_u)
    U_hat = wp.zeros((n_max, size), dtype=wp.float32, device=device)
    P_hat = wp.zeros((n_max, size), dtype=wp.float32, device=device)
    for flat, hat in ((flat_u, U_hat), (flat_p, P_hat)):  # the rings, transformed (as they would be kept)
        wp.utils.array_scan(flat, S, inclusive=True)
        wp.launch(kc.haar_coefficients, dim=(n_max, size), inputs=[S, size, hat], device=device)
    new = wp.array(rows_of(U[:1]).ravel(), dtype=wp.float64, device=device)  # one step's new vector
    S1, new_hat = wp.empty_like(new), wp.zeros((1, size), dtype=wp.float32, device=device)
    h_hat = wp.zeros((1, size), dtype=wp.float32, device=device)
    h_out = wp.zeros((1, size), dtype=wp.float32, device=device)
    for r in ratios:
        bounds, cols, vals = pack_rows(kept[r])
        bd = wp.array(bounds, dtype=wp.int64, device=device)
        cd = wp.array(cols, dtype=wp.uint16, device=device)
        vd = wp.array(vals, dtype=wp.float32, device=device)

        def step_fn() -> None:
            for _ in range(2):  # u and p of the step enter the ring: two forward transforms
                wp.utils.array_scan(new, S1, inclusive=True)
                wp.launch(kc.haar_coefficients, dim=(1, size), inputs=[S1, size, new_hat], device=device)
            wp.launch_tiled(kc.history_spmv, dim=size, block_dim=int(kc.SPMV_BLOCK), device=device,
                            inputs=[bd, cd, vd, U_hat, P_hat, step, h_hat])
            wp.launch(kc.haar_inverse, dim=(1, size), inputs=[h_hat, h_out], device=device)

        comp_s = timed(step_fn, args.reps, device)
        got = np.empty(n)
        got[perm] = h_out.numpy()[0, :n]
        # the dense kernel's h holds -H u + G p only (B = 0): compare directly
        err = float(np.linalg.norm(got - h_dense) / np.linalg.norm(h_dense))
        nbytes = int(bounds.nbytes + cols.nbytes + vals.nbytes)
        print(json.dumps({"case": f"compressed CR {r:g}", "device": device.name, "N": ops.n_nodes, "n_max": n_max,
                          "history_ms": 1e3 * comp_s, "speedup_vs_dense": dense_s / comp_s,
                          "matrix_bytes": nbytes, "memory_ratio_vs_dense": dense_bytes / nbytes,
                          "value_and_column_bytes": int(cols.nbytes + vals.nbytes),
                          "history_relative_error_smooth_rings": err, "compress_s_all_ratios": round(compress_s, 1)}),
              flush=True)


if __name__ == "__main__":
    main()
