"""Per-kernel device times of the compressed BEM history (issue 20), each kernel replayed 50 times
in one CUDA graph: the sparse sum for several work-item sizes, the row totals, the two-vector ring
update and the inverse transform. One JSON object.

    python tools/profile_bem_compressed.py --device cuda:0 --divisions 22 --ratio 32

The body is the bumpy cube of the paper's Table 1 (jelly, dt 0.01; N = 6 d^2 + 2 nodes). Every
chunk size must give the same history (``same_as_first``: the largest difference, float32
round-off of a different summation order).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--divisions", type=int, default=22)
    ap.add_argument("--ratio", type=float, default=32.0)
    ap.add_argument("--chunks", default="256,512,1024,2048")
    args = ap.parse_args()

    import warp as wp

    import wsim
    from wsim import mesh as wmesh
    from wsim.bem import build_operators, stepper
    from wsim.bem.compression import compress_history, pack_rows, work_items
    from wsim.device import quiet_warp, resolve_device
    from wsim.kernels import bem_compressed as kc
    from wsim.kernels import bem_compressed_warps as kw

    quiet_warp()
    dev = resolve_device(args.device)
    if not dev.is_cuda:
        raise SystemExit("profile_bem_compressed times CUDA graphs: give a CUDA device")
    cube = wmesh.bumpy_cube(size=0.45, divisions=args.divisions, amplitude=0.04)
    jelly = wsim.ElasticMaterial(mu=5e5, nu=0.5, rho=1e3, incompressible=True)
    ops = build_operators(cube, jelly, 0.01, device=dev, progress=False)
    ch = compress_history(ops, ratio=args.ratio, device=dev)
    size, n_max, n3 = ch.size, ops.n_max, 3 * ops.n_nodes
    b, c, v = pack_rows([*ch.H, *ch.G])
    cols = wp.array(c.reshape(-1, 4), dtype=kc.vec4us, device=dev)
    vals = wp.array(v.reshape(-1, 4), dtype=wp.vec4f, device=dev)
    rng = np.random.default_rng(0)
    X = wp.array(rng.standard_normal((2 * n_max, size)).astype(np.float32), device=dev)
    y = wp.zeros((1, size), dtype=wp.float32, device=dev)

    def timed(fn, reps: int = 50) -> float:
        fn()
        wp.synchronize_device(dev)
        with wp.ScopedCapture(device=dev) as cap:
            for _ in range(reps):
                fn()
        wp.capture_launch(cap.graph)
        wp.synchronize_device(dev)
        t0 = time.perf_counter()
        for _ in range(5):
            wp.capture_launch(cap.graph)
        wp.synchronize_device(dev)
        return (time.perf_counter() - t0) / (5 * reps)

    out: dict = {"gpu": dev.name, "N": ops.n_nodes, "ratio": args.ratio, "coefficients": int(np.count_nonzero(v)),
                 "stored": int(len(v)), "bytes": int(len(v) * 6)}
    first = None
    for chunk in (int(x) for x in args.chunks.split(",")):
        parts = work_items(b, chunk)
        im, ist, il, ri, rl = (wp.array(a, dtype=t, device=dev) for a, t in
                               zip(parts, (wp.uint8, wp.int64, wp.uint16, wp.int64, wp.int32)))
        items = len(parts[0])
        partial = wp.zeros(-(-items // int(kw.WARPS)) * int(kw.WARPS), dtype=wp.float32, device=dev)
        inputs = [im, ist, il, cols, vals, X, n_max, 7, partial]
        t_sum = timed(lambda: wp.launch_tiled(kw.chunk_sums_warps, dim=-(-items // int(kw.WARPS)),
                                              block_dim=32 * int(kw.WARPS), device=dev, inputs=inputs))
        t_rows = timed(lambda: wp.launch_tiled(kc.row_sums, dim=size, block_dim=int(kc.SPMV_BLOCK), device=dev,
                                               inputs=[ri, rl, partial, y]))
        got = y.numpy().copy()
        first = got if first is None else first
        out[f"chunk {chunk}"] = {"items": items, "sum_us": 1e6 * t_sum, "row_totals_us": 1e6 * t_rows,
                                 "GBps": len(v) * 6 / t_sum / 1e9, "same_as_first": float(np.abs(got - first).max())}
    sums = stepper.pass_buffers(2 * n_max, size, dev)
    U = wp.array(rng.standard_normal((n_max, n3)).astype(np.float32), device=dev)
    perm = wp.array(ch.perm.astype(np.int32), device=dev)
    hat = wp.zeros((2 * n_max, size), dtype=wp.float32, device=dev)
    out["ring_update_us"] = 1e6 * timed(lambda: stepper.haar_rows([(U, 2, 1), (U, 3, 1)], perm, size, sums, hat, 2, n_max))
    DQ = wp.zeros((n_max, n3, 6), dtype=wp.float32, device=dev)
    B = wp.zeros((n_max, 6), dtype=wp.float32, device=dev)
    h = wp.zeros(n3, dtype=wp.float32, device=dev)
    out["inverse_history_us"] = 1e6 * timed(lambda: wp.launch(kc.inverse_history, dim=n3, inputs=[y, perm, DQ, B, 7, h],
                                                              device=dev))
    print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
