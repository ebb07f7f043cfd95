"""BEM side of the point constraints: the linear response of node positions to point forces
(Eqs. 13-14, ``wsim.kernels.bem_constraints``) and the tractions that apply them.

``PointResponse`` holds what the response needs per node besides W = H_0^-1 G' (on the device in
``StepOperators``, or compressed: then ``response_rows`` rebuilds the rows the constraint points
need): 1 / a_j and C_j / a_j. It is immutable and shared like the operators.

The frame's angular response to a point force acts at the point itself (I^-1 l x f, ``BemBody``):
the traction f / a_j that carries it to the BEM spreads it over node j's hat function, whose
moment C_j / a_j acts at the hat's centroid, and a contact's two sides would then exert a net
torque on the pair (20 % of a glancing blow's angular momentum lost at 26 nodes a cube).

"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from wsim.bem.operators import PRECISIONS
from wsim.bem.stepper import StepOperators
from wsim.launch import concrete
from wsim.rigid import cross_matrix
from wsim.kernels import bem_constraints as kb


ROW_MEMO_NODES = 2048  # nodes whose rows of a compressed W are remembered (0.2 GB at N = 2906, 0.7 at 10k;
# a single call asking for more keeps them all until the next)


@dataclass(frozen=True)
class PointResponse:
    """Per-node pieces of K (``wsim.kernels.bem_constraints``) on one device.

    Attributes:
        area: (N,) a_j = int N_j dGamma [m^2]; inv_area on the device.
        C_over_a: (N, 3, 3) C_j / a_j, the frame terms' alpha per unit force at node j (host).
    """

    area: np.ndarray
    inv_area: wp.array
    C_over_a: np.ndarray

    @classmethod
    def build(cls, so: StepOperators) -> PointResponse:
        ops = so.operators
        area = ops.surface.node_areas()
        n = ops.n_nodes
        C = ops.C.reshape(3, n, 3).transpose(1, 0, 2) / area[:, None, None]  # C_j / a_j, (N, 3, 3)
        return cls(area=area, inv_area=wp.array(1.0 / area, dtype=wp.float64, device=so.device),
                   C_over_a=np.ascontiguousarray(C))


def point_torques(pr: PointResponse, points) -> np.ndarray:
    """(m, 3, 3) sum_b w_jb C(n_jb) / a(n_jb): the BEM's frame terms' alpha per unit force (frame
    axes) at each of ``points`` (``wsim.constraints.PointRefs``)."""
    return np.einsum("mk,mkab->mab", points.w, pr.C_over_a[points.ids])


def response_matrix(so: StepOperators, pr: PointResponse, points, Rk: np.ndarray, R1: np.ndarray,
                    lin_a: np.ndarray, lin_c: np.ndarray, torque: np.ndarray) -> tuple[wp.array, wp.array]:
    """K (3m, 3m) [m/N] of the m ``points`` (``wsim.constraints.PointRefs``; float64, on the device)
    and its transpose; lin_a, lin_c, torque (m, 3, 3) as in ``response_blocks`` (``frame_terms``)."""
    d = so.device
    m = len(points)
    K = wp.empty((3 * m, 3 * m), dtype=wp.float64, device=d)
    Kt = wp.empty((3 * m, 3 * m), dtype=wp.float64, device=d)

    def mats(a: np.ndarray) -> wp.array:
        return wp.array(np.ascontiguousarray(a, dtype=np.float64), dtype=wp.mat33d, device=d)

    W, row_of = response_rows(so, points.ids.ravel())
    wp.launch(concrete(kb.response_blocks, W=(2, W.dtype)), dim=(m, m), device=d,
              inputs=[W, row_of, wp.array(points.ids.astype(np.int32), dtype=wp.vec3i, device=d),
                      wp.array(points.w, dtype=wp.vec3d, device=d),
                      wp.mat33d(*Rk.ravel()), wp.mat33d(*R1.ravel()), pr.inv_area, mats(torque), mats(lin_a),
                      mats(lin_c), wp.float64(1.0 / so.operators.mass), K, Kt])
    return K, Kt


def frame_terms(so: StepOperators, points, lever: np.ndarray, R: np.ndarray, dt: float,
                frame_update: bool) -> tuple[np.ndarray, np.ndarray]:
    """(lin_a, lin_c) of ``response_blocks`` for ``points`` with world lever arms ``lever`` (m, 3)."""
    m = len(points)
    if frame_update:
        lin_a = np.broadcast_to(dt * dt * np.eye(3), (m, 3, 3))
        return lin_a, -dt * dt * cross_matrix(np.reshape(lever, (m, 3)))
    E = np.einsum("mk,mkab->mab", points.w, so.E.reshape(-1, 3, 6)[points.ids])  # (m, 3, 6) at the points
    return -R @ E[:, :, :3] @ R.T, -R @ E[:, :, 3:] @ R.T


def response_rows(so: StepOperators, nodes: np.ndarray) -> tuple[wp.array, wp.array]:
    """(W, row_of): rows of W = H_0^-1 G' for the kernels, node n's three rows at 3 row_of[n]..
    The dense W itself with the identity map, or, for compressed operators, the rows of ``nodes``
    alone rebuilt from the kept coefficients (``CompressedMatrix.rows``: log2(size) + 1 sparse
    rows and one inverse transform each, ~1 ms a node on the host at N = 2906; other nodes map
    to -1), each node's once while it stays in the operators' memo (``StepOperators.W_rows``, at
    most ROW_MEMO_NODES nodes: 12 N float32 bytes each); the device arrays of the last node set
    are kept and returned again for the same set."""
    if so.compressed is None:
        return so.H0_inv_Gp, so.node_rows
    nodes = np.unique(np.asarray(nodes, dtype=np.int64))
    key = nodes.tobytes()
    if so.W_uploaded.get("nodes") == key:
        return so.W_uploaded["arrays"]
    memo = so.W_rows  # W is constant: a node's rows are rebuilt once (contacts move slowly)
    new = [int(n) for n in nodes if int(n) not in memo]
    if new:
        if len(memo) + len(new) > ROW_MEMO_NODES:
            memo.clear()  # and this call's remembered nodes with it: rebuild them all
            new = [int(n) for n in nodes]
        rebuilt = so.compressed.H0_inv_Gp.rows((3 * np.asarray(new)[:, None] + np.arange(3)).ravel())
        dtype = PRECISIONS[so.operators.precision]
        for i, n in enumerate(new):
            memo[n] = rebuilt[3 * i: 3 * i + 3].astype(dtype)
    row_of = np.full(so.operators.n_nodes, -1, dtype=np.int32)
    row_of[nodes] = np.arange(len(nodes), dtype=np.int32)
    W = np.concatenate([memo[int(n)] for n in nodes]) if len(nodes) else np.zeros((0, so.size))
    arrays = (wp.array(W, dtype=so.dtype, device=so.device), wp.array(row_of, dtype=wp.int32, device=so.device))
    so.W_uploaded.update(nodes=key, arrays=arrays)  # one entry: the rows are constant, only the set changes
    return arrays


def add_point_displacement(so: StepOperators, nodes: np.ndarray, p: np.ndarray, u: np.ndarray) -> np.ndarray:
    """u + W[:, nodes] p for the (m, 3) frame-axes tractions p on ``nodes`` (u: (3N,) host)."""
    if so.compressed is not None:  # every row: the compressed product with the traction field
        p_full = np.zeros((so.operators.n_nodes, 3))
        np.add.at(p_full, nodes, p)
        return u + so.compressed.H0_inv_Gp.matvec(p_full.reshape(-1))
    every = np.arange(so.operators.n_nodes)
    return u + point_displacement(so, every, nodes, p).reshape(-1)


HOST_PAIRS = 1 << 14  # (row, node) pairs up to which ``point_displacement`` runs in numpy on the host


def point_displacement(so: StepOperators, rows: np.ndarray, nodes: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(len(rows), 3) displacement W[rows, nodes] p of the (m, 3) frame-axes tractions p on ``nodes``.
    Up to ``HOST_PAIRS`` (row, node) pairs of dense operators on the host copy of W: the product is
    microseconds there, where a launch costs its uploads and a read-back (a small body's contact
    steps make a few of these each)."""
    if so.compressed is None and len(rows) * len(nodes) <= HOST_PAIRS:
        W = so.operators.H0_inv_Gp
        r = (3 * np.asarray(rows, dtype=np.int64)[:, None] + np.arange(3)).ravel()
        c = (3 * np.asarray(nodes, dtype=np.int64)[:, None] + np.arange(3)).ravel()
        return (W[np.ix_(r, c)].astype(np.float64) @ np.asarray(p, dtype=np.float64).reshape(-1)).reshape(-1, 3)
    d = so.device
    out = wp.empty(len(rows), dtype=wp.vec3d, device=d)
    W, row_of = response_rows(so, rows)
    wp.launch(concrete(kb.point_rows, W=(2, W.dtype)), dim=len(rows), device=d,
              inputs=[W, row_of, wp.array(rows.astype(np.int32), dtype=wp.int32, device=d),
                      wp.array(nodes.astype(np.int32), dtype=wp.int32, device=d),
                      wp.array(np.ascontiguousarray(p), dtype=wp.vec3d, device=d), out])
    return out.numpy()
