"""Speed against accuracy of the BEM quadrature knobs (``wsim.bem.quadrature.Quadrature``).

Workload: a solid sphere (icosphere, 162 or 642 nodes) under uniform pressure at one complex
frequency, solved with ``laplace_matrices``; its radial displacement has a closed form (the
analytic check of tests/test_bem_operators.py). For each knob setting the study prints one JSON
line: device, nodes, knobs, seconds of one Laplace-domain assembly (warm), the error of H and G
against a reference assembly with much finer rules (subdivision 8, order 5, singular order 20),
and the radial-displacement error against the analytic solution (which also contains the
polyhedral-geometry error, the floor no quadrature can pass).

    python tools/study_bem_quadrature.py --device cpu --sub 2
"""

from __future__ import annotations

import argparse
import json
import time

SETTINGS = [
    dict(subdivision=1),
    dict(subdivision=1, order=2),
    dict(),  # the paper's rule: 4 sub-triangles x 9 points, polar order 8
    dict(subdivision=4),
    dict(singular_order=4),
    dict(singular_order=16),
    dict(near_ratio=0.0),
    dict(near_levels=1),
]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default=None)
    ap.add_argument("--sub", type=int, default=2, help="icosphere subdivisions (2: 162 nodes, 3: 642)")
    ap.add_argument("--s", type=complex, default=150 + 60j)
    args = ap.parse_args()

    import numpy as np
    import trimesh

    import wsim
    from wsim.bem.assembly import laplace_matrices
    from wsim.device import quiet_warp, resolve_device

    quiet_warp()
    dev = resolve_device(args.device)
    mat = wsim.ElasticMaterial(mu=5e5, nu=0.3, rho=1000.0)
    a, P, s = 0.5, 1000.0, args.s
    k = s / mat.c1
    sh, ch = np.sinh(k * a), np.cosh(k * a)
    A = -P / (mat.lam * k**2 * sh / a + 2 * mat.mu * (k**2 * a**2 * sh - 2 * k * a * ch + 2 * sh) / a**3)
    exact = A * (k * a * ch - sh) / a**2
    m = trimesh.creation.icosphere(subdivisions=args.sub, radius=a)
    normal = m.vertices / np.linalg.norm(m.vertices, axis=1, keepdims=True)
    laplace_matrices(m.vertices, m.faces, mat, s, device=dev, subdivision=1)  # compile
    H_ref, G_ref = laplace_matrices(m.vertices, m.faces, mat, s, device=dev, subdivision=8, order=5, singular_order=20)
    for knobs in SETTINGS:
        t0 = time.perf_counter()
        H, G = laplace_matrices(m.vertices, m.faces, mat, s, device=dev, **knobs)
        seconds = time.perf_counter() - t0
        u = np.linalg.solve(H, G @ (-P * normal).ravel()).reshape(-1, 3)
        ur = np.sum(u * normal, axis=1)
        print(json.dumps({
            "device": dev.alias, "nodes": len(m.vertices), "s": str(s), "knobs": knobs or "default (paper)",
            "seconds": round(seconds, 4),
            "H_error": float(np.abs(H - H_ref).max() / np.abs(H_ref).max()),
            "G_error": float(np.abs(G - G_ref).max() / np.abs(G_ref).max()),
            "radial_error_vs_analytic": float(np.abs(ur - exact).max() / abs(exact)),
        }), flush=True)


if __name__ == "__main__":
    main()
