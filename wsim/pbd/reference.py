"""A numpy implementation of the XPBD frame, for validation and as the CPU baseline in benchmarks.

It computes what ``PbdBody`` computes (same model, same colour order, same formulas) with
numpy fancy indexing, one vectorized update per colour, in float64. It is independent of the
Warp kernels, so agreement between the two checks the kernels' indexing, colouring and
launch schedule; and it is what a user without Warp would write, so benchmarks time it beside
the Warp CPU and GPU paths. Covers gravity, pins, kinematic targets, every constraint family,
the global volume constraint and ground planes (no mesh colliders, no drag).
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from wsim.pbd.model import ConstraintFamily, PbdModel, hinge_edge_layout


def _delta_lambda(C, lam, w_grad2, dC, alpha, beta, h):
    alpha_t = alpha / (h * h)
    gamma = beta / h
    denom = (1.0 + gamma) * w_grad2 + alpha_t
    safe = np.where(denom > 0.0, denom, 1.0)
    return np.where(denom > 0.0, (-C - alpha_t * lam - gamma * dC) / safe, 0.0)


def _wrap(a: np.ndarray) -> np.ndarray:
    return np.where(a > np.pi, a - 2 * np.pi, np.where(a < -np.pi, a + 2 * np.pi, a))


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", a, b)


def _project_family(f: ConstraintFamily, x, x_prev, w, lam, beta, h) -> None:
    for c in range(f.colours):
        sl = slice(int(f.offsets[c]), int(f.offsets[c + 1]))
        idx = f.indices[sl]
        if f.kind == "distance":
            i, j = idx[:, 0], idx[:, 1]
            d = x[i] - x[j]
            length = np.linalg.norm(d, axis=1)
            ok = (w[i] + w[j] > 0) & (length > 1e-12)
            n = d / np.where(length > 1e-12, length, 1.0)[:, None]
            grads = [n, -n]
            C = length - f.rest[sl]
            dC = length - np.linalg.norm(x_prev[i] - x_prev[j], axis=1)
        elif f.kind == "bending":
            a, b, p, q = idx.T
            w1, w2, e0, e1 = x[a], x[b], x[p], x[q]
            E = e1 - e0
            len2 = _dot(E, E)
            n1 = np.cross(E, w1 - e0)
            n2 = np.cross(e0 - e1, w2 - e1)
            n1sq, n2sq = _dot(n1, n1), _dot(n2, n2)
            ok = (w[a] + w[b] + w[p] + w[q] > 0) & (len2 > 1e-20) & (n1sq > 1e-24) & (n2sq > 1e-24)
            len2s, n1s, n2s = (np.where(ok, v, 1.0) for v in (len2, n1sq, n2sq))
            elen = np.sqrt(len2s)
            g1 = n1 * (-elen / n1s)[:, None]
            g2 = n2 * (-elen / n2s)[:, None]
            t1 = _dot(w1 - e0, E) / len2s
            t2 = _dot(w2 - e0, E) / len2s
            g3 = -((1 - t1)[:, None] * g1 + (1 - t2)[:, None] * g2)
            g4 = -(t1[:, None] * g1 + t2[:, None] * g2)
            n1h = n1 / np.sqrt(n1s)[:, None]
            n2h = n2 / np.sqrt(n2s)[:, None]
            theta = np.arctan2(_dot(np.cross(n1h, n2h), E / elen[:, None]), _dot(n1h, n2h))
            C = _wrap(theta - f.rest[sl])
            pw1, pw2, pe0, pe1 = x_prev[a], x_prev[b], x_prev[p], x_prev[q]
            pE = pe1 - pe0
            pn1, pn2 = np.cross(pE, pw1 - pe0), np.cross(pe0 - pe1, pw2 - pe1)
            theta_prev = np.arctan2(_dot(np.cross(pn1, pn2), pE) / np.maximum(np.linalg.norm(pE, axis=1), 1e-30), _dot(pn1, pn2))
            dC = _wrap(theta - theta_prev)
            grads = [g1, g2, g3, g4]
        else:  # tet_volume
            i0, i1, i2, i3 = idx.T
            d1, d2, d3 = x[i1] - x[i0], x[i2] - x[i0], x[i3] - x[i0]
            g1, g2, g3 = np.cross(d2, d3) / 6.0, np.cross(d3, d1) / 6.0, np.cross(d1, d2) / 6.0
            grads = [-(g1 + g2 + g3), g1, g2, g3]
            C = _dot(d1, g1) - f.rest[sl]
            p0 = x_prev[i0]
            dC = _dot(d1, g1) - _dot(x_prev[i1] - p0, np.cross(x_prev[i2] - p0, x_prev[i3] - p0)) / 6.0
            ok = w[i0] + w[i1] + w[i2] + w[i3] > 0
        cols = idx.T
        w_grad2 = sum(w[k] * _dot(g, g) for k, g in zip(cols, grads))
        dl = np.where(ok, _delta_lambda(C, lam[sl], w_grad2, dC, f.compliance[sl], beta, h), 0.0)
        lam[sl] += dl
        for k, g in zip(cols, grads):
            x[k] += g * (w[k] * dl)[:, None]


def _project_volume(model: PbdModel, x, w, lam_v: list[float], h: float) -> None:
    vol = model.volume
    n = model.n_surface
    f = model.faces
    o = x[0]
    xs = x[:n] - o
    grad = np.zeros((n, 3))
    # gradient of (1/6) sum_f a.(b x c): for each corner, the cross product of the other two (cyclic)
    np.add.at(grad, f[:, 0], np.cross(xs[f[:, 1]], xs[f[:, 2]]))
    np.add.at(grad, f[:, 1], np.cross(xs[f[:, 2]], xs[f[:, 0]]))
    np.add.at(grad, f[:, 2], np.cross(xs[f[:, 0]], xs[f[:, 1]]))
    grad /= 6.0
    V = _dot(xs, grad).sum() / 3.0
    w_grad2 = (w[:n] * _dot(grad, grad)).sum()
    alpha_t = vol.compliance / (h * h)
    denom = w_grad2 + alpha_t
    d = (-(V - vol.target_volume) - alpha_t * lam_v[0]) / denom if denom > 0 else 0.0
    lam_v[0] += d
    x[:n] += grad * (w[:n] * d)[:, None]


def _ground(x, x_prev, x_pred, w, normal, height, margin, mu) -> None:
    depth = height + margin - x @ normal
    hit = (depth > 0.0) & (w > 0.0)
    if not np.any(hit):
        return
    # pre-stabilization: overlap present at the substep start moves x_prev and x_pred too
    shift = np.minimum(depth[hit], np.maximum(height + margin - x_prev[hit] @ normal, 0.0))
    x_prev[hit] += normal * shift[:, None]
    x_pred[hit] += normal * shift[:, None]
    p = x[hit] + normal * depth[hit, None]
    dx = p - x_prev[hit]
    dx_t = dx - normal * (dx @ normal)[:, None]
    t_len = np.linalg.norm(dx_t, axis=1)
    limit = mu * depth[hit]
    scale = np.where(t_len < limit, 1.0, limit / np.where(t_len > 0, t_len, 1.0))
    x[hit] = p - dx_t * np.where(t_len > 0, scale, 0.0)[:, None]


def _project_hinges_with_edges(b: ConstraintFamily, d: ConstraintFamily, edge: np.ndarray, x, x_prev, w, lam_b,
                               lam_d, beta, h) -> None:
    """Colour by colour: the colour's hinges' edges (distance constraints of ``d``), then the
    hinges; an edge's particles are its hinge's, so within a colour this is each hinge's edge
    right before it (``kernels.pbd.solve_hinge_edge``)."""
    for c in range(b.colours):
        lo, hi = int(b.offsets[c]), int(b.offsets[c + 1])
        k = edge[lo:hi]
        k = k[k >= 0]
        if len(k):
            part = ConstraintFamily(kind="distance", indices=d.indices[k], rest=d.rest[k], compliance=d.compliance[k],
                                    offsets=np.array([0, len(k)]))
            lam = lam_d[k]
            _project_family(part, x, x_prev, w, lam, beta, h)
            lam_d[k] = lam
        hinges = ConstraintFamily(kind="bending", indices=b.indices[lo:hi], rest=b.rest[lo:hi],
                                  compliance=b.compliance[lo:hi], offsets=np.array([0, hi - lo]))
        _project_family(hinges, x, x_prev, w, lam_b[lo:hi], beta, h)


def run_frame(
    model: PbdModel,
    x: np.ndarray,
    v: np.ndarray,
    inv_mass: np.ndarray,
    gravity: np.ndarray,
    frame_dt: float,
    substeps: int,
    iterations: int,
    damping: float,
    planes: Sequence[tuple[np.ndarray, float, float]] = (),
    margin: float = 0.0,
    kinematic: tuple[np.ndarray, Callable[[int], np.ndarray]] | None = None,
    hinge_edges: bool = False,
) -> None:
    """Advance (x, v) in place by one frame of ``substeps`` substeps.

    ``planes`` are (unit normal, height, friction); ``kinematic`` is (indices, s -> (K, 3) targets
    at the end of substep s = 1..substeps). ``hinge_edges``: each hinge's edge is projected just
    before it, colour by colour (``wsim.pbd.model.hinge_edge_layout``; what ``PbdBody`` does for a
    surface body with stretch and bending).
    """
    families: list[ConstraintFamily] = list(model.families)
    edge = None
    kinds = {f.kind: f for f in families}
    if hinge_edges and "distance" in kinds and "bending" in kinds:
        fused, edge = hinge_edge_layout(kinds["distance"], kinds["bending"], model.n_particles)
        families = [fused if f is kinds["distance"] else f for f in families]
    h = frame_dt / substeps
    free = inv_mass > 0.0
    for s in range(1, substeps + 1):
        x_prev = x.copy()
        v[free] += gravity * h
        v[~free] = 0.0
        x[free] += v[free] * h
        x_pred = x.copy()  # kinematic particles: x_pred = x_prev, so they get their handle's velocity
        if kinematic is not None:
            x[kinematic[0]] = kinematic[1](s)
        lams = [np.zeros(f.count) for f in families]
        lam_v = [0.0]
        for _ in range(iterations):
            for f, lam in zip(families, lams):
                if f.kind == "bending" and edge is not None:
                    di = next(i for i, g in enumerate(families) if g.kind == "distance")
                    _project_hinges_with_edges(f, families[di], edge, x, x_prev, inv_mass, lam, lams[di], damping, h)
                else:
                    _project_family(f, x, x_prev, inv_mass, lam, damping, h)
            if model.volume is not None:
                _project_volume(model, x, inv_mass, lam_v, h)
            for normal, height, mu in planes:
                _ground(x, x_prev, x_pred, inv_mass, normal, height, margin, mu)
        v += (x - x_pred) / h
