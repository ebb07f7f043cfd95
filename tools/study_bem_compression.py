"""The paper's Fig. 7 (issue 20): relative Frobenius error of the compressed H_1 of the bumpy cube
against the compression ratio, for no reordering, vertex ("v"), coordinate ("c") and both
("v+c") reorderings, naive pruning of the raw entries, and (extra) reverse Cuthill-McKee in place of
the Morton node order. Prints one JSON line per (variant, CR) and writes a PNG.

    python tools/study_bem_compression.py [--divisions 5] [--device cpu] [--png out.png]

The paper's cube is N = 3000 (divisions 22 here, a GPU job); the default is small enough for a
CPU in about a minute. The errors are exact (the n x n part of the reconstruction against H_1).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

import wsim
from wsim import mesh as wmesh
from wsim.bem import build_operators
from wsim.bem.compression import compress, node_order, permutation, prune, transform

CRS = (2, 4, 8, 16, 32, 64, 128)


def bound_errors(H: np.ndarray, perm: np.ndarray, crs=CRS) -> list[float]:
    """The dropped coefficients' norm over ||H||_F at each CR, from one transform (a bound on the
    reconstruction's error, equal to it without padding; for sizes where reconstructing is slow)."""
    c = transform(H, perm)
    mags = np.sort(np.abs(c).ravel())[::-1] ** 2
    total = float(mags.sum())
    tail = np.concatenate([np.cumsum(mags[::-1])[::-1], [0.0]])  # tail[k] = sum of all but the k largest
    return [float(np.sqrt(tail[int(round(H.size / cr))] / total)) for cr in crs]


def errors(H: np.ndarray, surface, crs=CRS, exact: bool = True) -> dict[str, list[float]]:
    """Relative Frobenius error of H compressed at each CR, per variant (exact, reconstructed, or
    with ``exact=False`` the bound of ``bound_errors``)."""
    n_nodes = surface.n_nodes
    rcm = node_order(surface.nodes, surface.faces, surface.vertex, "rcm")
    morton = node_order(surface.nodes, surface.faces, surface.vertex, "morton")
    variants = {
        "none": permutation(n_nodes, "none"),
        "v": permutation(n_nodes, "v", morton),
        "c": permutation(n_nodes, "c"),
        "v+c": permutation(n_nodes, "v+c", morton),
        "v+c rcm": permutation(n_nodes, "v+c", rcm),
    }
    norm = np.linalg.norm(H)
    out: dict[str, list[float]] = {k: [] for k in [*variants, "prune"]}
    if not exact:
        for name, perm in variants.items():
            out[name] = bound_errors(H, perm, crs)
    for cr in crs:
        if exact:
            for name, perm in variants.items():
                c = compress(H, perm, ratio=cr)
                out[name].append(float(np.linalg.norm(c.to_dense() - H) / norm))
        out["prune"].append(prune(H, cr)[1])
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--divisions", type=int, default=5)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--png", default=None)
    ap.add_argument("--bound", action="store_true", help="the dropped-coefficient bound instead of reconstructing (large N)")
    args = ap.parse_args()
    cube = wmesh.bumpy_cube(size=0.45, divisions=args.divisions, amplitude=0.04)
    jelly = wsim.ElasticMaterial(mu=5e5, nu=0.5, rho=1e3, incompressible=True)  # the paper's bumpy cube (Table 1)
    t = time.perf_counter()
    ops = build_operators(cube, jelly, 0.01, device=args.device, precision="float64")
    build_s = time.perf_counter() - t
    H1 = np.asarray(ops.H[1], dtype=np.float64)
    t = time.perf_counter()
    res = errors(H1, ops.surface, exact=not args.bound)
    for name, errs in res.items():
        for cr, e in zip(CRS, errs):
            print(json.dumps({"matrix": "H_1", "mesh": f"bumpy_cube divisions={args.divisions}", "N": ops.surface.n_nodes,
                              "n_max": ops.n_max, "variant": name, "CR": cr, "relative_frobenius_error": e,
                              "error": "exact" if not args.bound or name == "prune" else "bound (dropped coefficients)"}))
    print(json.dumps({"build_s": build_s, "study_s": time.perf_counter() - t, "device": args.device}))
    if args.png:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(6, 4))
        for name, errs in res.items():
            ax.loglog(CRS, errs, "o-" if name != "prune" else "k--", label=name)
        ax.set_xlabel("compression ratio CR")
        ax.set_ylabel("relative Frobenius error of H_1")
        ax.set_title(f"bumpy cube, N = {ops.surface.n_nodes} (paper's Fig. 7)")
        ax.legend()
        ax.grid(True, which="both", alpha=0.3)
        fig.tight_layout()
        fig.savefig(args.png, dpi=120)


if __name__ == "__main__":
    main()
