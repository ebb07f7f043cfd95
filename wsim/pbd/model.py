"""The immutable PBD model: particles, masses and coloured constraint families.

A model is built once from (mesh, tets, material, options), cached by content hash through
``wsim.cache`` and shared by every body that uses the same key. Per-body data (which particles
are pinned or driven, positions, velocities, multipliers) lives in the body's state.

Compliances come from the material so that ``E``, ``nu`` and ``rho`` mean something and a
scene does not need retuning when the mesh resolution changes. The mapping (all SI):

- Edge stretch, surface-only body: a membrane of thickness h has energy density (E h / 2) eps^2
  per unit area; giving each edge a third of its two faces' area A_e,
  alpha_e = L0^2 / (E h A_e)  [m/N].
- Tet body: edge springs plus one volume constraint per tet, matched to linear elasticity
  (energy density mu eps:eps + (lambda/2) tr(eps)^2). An edge of rest length L0 carrying V_e (a
  sixth of the volume of each tet around it) with alpha_e = L0^2 / (s V_e) stores
  (s/2) V_e eps_nn^2, eps_nn = n.eps.n its strain; averaged over directions
  <eps_nn^2> = (2 eps:eps + tr(eps)^2) / 15, so the springs alone are an isotropic solid with
  mu_s = lambda_s = s / 15 (a central-force network obeys the Cauchy relation, nu = 1/4). Hence
  s = 15 mu gives the shear modulus, and the tet volumes add the rest of lambda:
  alpha_t = V_t / (lambda - mu) [m^3/Pa] (the energy (lambda - mu)/2 (dV/V)^2 V). For nu < 1/4
  (lambda < mu) the volume term would need a negative stiffness: the springs then take
  s = 6 E (Young's modulus E at nu = 1/4) and there is no volume term. The earlier mapping
  (s = E, alpha_t = V_t / K) made the solid ~5x too soft in shear: a ball sagged 65 mm on the
  ground against a Hertz estimate of 29 mm.
- Dihedral bending: a plate of bending modulus D = E h^3 / (12 (1 - nu^2)) bent to curvature
  1/R stores (D/2) R^-2 per unit area; a hinge of length |e| between faces of area A1, A2 bent
  by theta stores (1/2) theta^2 / alpha_b, which matches for alpha_b = (A1 + A2) / (D |e|^2).
- Global volume: the energy (K/2) (dV)^2 / V0 of a bulk modulus K gives alpha_V = V0 / K [m^3/Pa]
  (0 in the incompressible limit).

Masses: a tet body lumps rho V_t / 4 onto each tet vertex; a surface-only body is a solid of
density rho whose mass rho V0 is lumped onto the surface vertices in proportion to their area.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from wsim import mesh as wmesh
from wsim.errors import InvalidMesh, InvalidParameter
from wsim.materials import ElasticMaterial
from wsim.colouring import colour_smallest_last

#: Bump whenever the arrays or their meaning change, so cached models are rebuilt.
#: 2: tets="auto" classifies with the float32 BVH winding-number test of wsim.mesh.inside (was an
#: exact float64 oracle); equal on every tested shape, but points within ~1e-7 of the size from
#: the surface may now fall the other way.
#: 3: tet bodies map E, nu to edge springs s = 15 mu and tet volumes lambda - mu (were E and K).
#: 4: constraints coloured greedily in smallest-last order (``wsim.colouring``; were Luby rounds).
MODEL_FORMAT_VERSION = 4

FAMILY_KINDS = ("distance", "bending", "tet_volume")


@dataclass(frozen=True)
class ConstraintFamily:
    """One kind of constraint, sorted by colour.

    Attributes:
        kind: "distance" (arity 2), "bending" (arity 4: wing, wing, edge, edge) or "tet_volume" (arity 4).
        indices: (K, arity) int32 particle indices, colour-sorted.
        rest: (K,) float64 rest values (length [m], dihedral angle [rad], volume [m^3]).
        compliance: (K,) float64 XPBD compliances (units in the module docstring).
        offsets: (C + 1,) int64: colour c holds constraints offsets[c] .. offsets[c + 1] - 1.
    """

    kind: str
    indices: np.ndarray
    rest: np.ndarray
    compliance: np.ndarray
    offsets: np.ndarray

    @property
    def count(self) -> int:
        return int(self.indices.shape[0])

    @property
    def colours(self) -> int:
        return int(len(self.offsets) - 1)

    def active(self, kinematic: np.ndarray) -> ConstraintFamily:
        """The family without its constraints whose particles are all kinematic (pinned or driven:
        their projection moves nothing, ``kernels.pbd``), in the same colour order, and without
        the colours that leaves empty: each remaining constraint is projected exactly as before,
        in the same order, in fewer launches (a pinned region's colours, such as those of a
        high-valence vertex inside it, cost nothing)."""
        keep = ~np.all(np.asarray(kinematic, dtype=bool)[self.indices], axis=1)
        if keep.all():
            return self
        colour = np.repeat(np.arange(self.colours), np.diff(self.offsets))
        counts = np.bincount(colour[keep], minlength=self.colours)
        counts = counts[counts > 0]
        return ConstraintFamily(kind=self.kind, indices=self.indices[keep], rest=self.rest[keep],
                                compliance=self.compliance[keep],
                                offsets=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64))


def hinge_edge_layout(d: ConstraintFamily, b: ConstraintFamily, n: int) -> tuple[ConstraintFamily, np.ndarray]:
    """Each hinge of ``b`` paired with its edge's distance constraint in ``d`` (n particles), to
    be projected together (``kernels.pbd.solve_hinge_edge``): the distance family reordered as
    its unpaired constraints in their colours (boundary edges, springs) followed by the paired
    ones, outside every colour (``offsets`` cover the unpaired only), and each hinge's edge index
    in it, -1 for none. An edge goes to one hinge (the first; a closed manifold surface has one
    hinge per edge)."""
    pair = np.sort(np.asarray(d.indices, dtype=np.int64), axis=1)
    key = pair[:, 0] * n + pair[:, 1]
    hinge_edge = np.sort(np.asarray(b.indices, dtype=np.int64)[:, 2:4], axis=1)
    want = hinge_edge[:, 0] * n + hinge_edge[:, 1]
    order = np.argsort(key, kind="stable")
    at = np.minimum(np.searchsorted(key[order], want), len(key) - 1)
    edge = np.where(key[order][at] == want, order[at], -1)
    taken = np.flatnonzero(edge >= 0)
    _, first = np.unique(edge[taken], return_index=True)
    keep = np.zeros(len(edge), dtype=bool)
    keep[taken[first]] = True
    edge[~keep] = -1
    covered = np.zeros(d.count, dtype=bool)
    covered[edge[edge >= 0]] = True
    unpaired, paired = np.flatnonzero(~covered), np.flatnonzero(covered)
    perm = np.concatenate([unpaired, paired])
    colour = np.repeat(np.arange(d.colours), np.diff(d.offsets))
    counts = np.bincount(colour[unpaired], minlength=d.colours)
    counts = counts[counts > 0]
    new_of_old = np.empty(d.count, dtype=np.int64)
    new_of_old[perm] = np.arange(d.count)
    fused = ConstraintFamily(kind="distance", indices=d.indices[perm], rest=d.rest[perm], compliance=d.compliance[perm],
                             offsets=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64))
    return fused, np.where(edge >= 0, new_of_old[np.maximum(edge, 0)], -1).astype(np.int32)


@dataclass(frozen=True)
class GlobalVolume:
    """Enclosed-volume constraint C = V(x) - inflation * V0 on the closed surface.

    ``vertex_face_start``/``vertex_faces`` is the vertex -> incident-face adjacency (CSR), so the
    gradient is gathered per vertex without atomics.
    """

    rest_volume: float
    target_volume: float
    compliance: float
    vertex_face_start: np.ndarray
    vertex_faces: np.ndarray

    def face_pairs(self, faces: np.ndarray) -> np.ndarray:
        """(E, 2) int32: for each entry of the adjacency, the incident face's other two vertices
        (b, c) read cyclically from the vertex (i, b, c), the order its gradient term
        (x_b - o) x (x_c - o) needs (``wsim.kernels.pbd.volume_gradient``)."""
        owner = np.repeat(np.arange(len(self.vertex_face_start) - 1), np.diff(self.vertex_face_start))
        f = np.asarray(faces)[self.vertex_faces]
        at = np.argmax(f == owner[:, None], axis=1)  # where the vertex sits in its face
        rows = np.arange(len(f))
        return np.stack([f[rows, (at + 1) % 3], f[rows, (at + 2) % 3]], axis=1).astype(np.int32)


@dataclass(frozen=True)
class PbdModel:
    """Particles and constraints of one PBD body; immutable and shareable.

    Attributes:
        rest_points: (P, 3) float64 rest positions [m]; the first ``n_surface`` are the surface vertices.
        faces: (M, 3) int32 surface triangles.
        mass: (P,) float64 particle masses [kg].
        families: non-empty constraint families in projection order.
        volume: the global volume constraint, or None.
    """

    rest_points: np.ndarray
    faces: np.ndarray
    n_surface: int
    mass: np.ndarray
    families: tuple[ConstraintFamily, ...]
    volume: GlobalVolume | None

    @property
    def n_particles(self) -> int:
        return int(self.rest_points.shape[0])

    # -- (de)serialization for the operator cache ------------------------------------------
    def to_arrays(self) -> dict[str, np.ndarray]:
        out: dict[str, np.ndarray] = {
            "rest_points": self.rest_points,
            "faces": self.faces,
            "n_surface": np.asarray(self.n_surface, dtype=np.int64),
            "mass": self.mass,
        }
        for f in self.families:
            out[f"{f.kind}.indices"] = f.indices
            out[f"{f.kind}.rest"] = f.rest
            out[f"{f.kind}.compliance"] = f.compliance
            out[f"{f.kind}.offsets"] = f.offsets
        if self.volume is not None:
            v = self.volume
            out["volume.scalars"] = np.array([v.rest_volume, v.target_volume, v.compliance], dtype=np.float64)
            out["volume.vertex_face_start"] = v.vertex_face_start
            out["volume.vertex_faces"] = v.vertex_faces
        return out

    @staticmethod
    def from_arrays(a: dict[str, np.ndarray]) -> PbdModel:
        families = tuple(
            ConstraintFamily(k, a[f"{k}.indices"], a[f"{k}.rest"], a[f"{k}.compliance"], a[f"{k}.offsets"])
            for k in FAMILY_KINDS
            if f"{k}.indices" in a
        )
        volume = None
        if "volume.scalars" in a:
            s = a["volume.scalars"]
            volume = GlobalVolume(
                float(s[0]), float(s[1]), float(s[2]), a["volume.vertex_face_start"], a["volume.vertex_faces"]
            )
        return PbdModel(
            rest_points=a["rest_points"],
            faces=a["faces"],
            n_surface=int(a["n_surface"]),
            mass=a["mass"],
            families=families,
            volume=volume,
        )


def _family(kind: str, indices: np.ndarray, rest: np.ndarray, compliance: np.ndarray, n: int) -> ConstraintFamily:
    order, offsets = colour_smallest_last(indices, n)
    return ConstraintFamily(
        kind=kind,
        indices=np.ascontiguousarray(indices[order], dtype=np.int32),
        rest=np.ascontiguousarray(rest[order], dtype=np.float64),
        compliance=np.ascontiguousarray(compliance[order], dtype=np.float64),
        offsets=offsets,
    )


def _override(value: float | None, default: np.ndarray, what: str) -> np.ndarray:
    if value is None:
        return default
    v = float(value)
    if not np.isfinite(v) or v < 0.0:
        raise InvalidParameter(f"{what} = {value} must be a finite number >= 0")
    return np.full_like(default, v)


def _spring_modulus(material: ElasticMaterial) -> float:
    """s [Pa] of the tet-edge springs (module docstring): 15 mu, or 6 E where lambda < mu."""
    if material.incompressible or material.lam >= material.mu:
        return 15.0 * material.mu
    return 6.0 * material.E


def _volume_modulus(material: ElasticMaterial) -> float:
    """Modulus [Pa] of the per-tet volume constraints: lambda - mu (inf if incompressible, 0 if nu < 1/4)."""
    if material.incompressible:
        return np.inf
    return max(material.lam - material.mu, 0.0)


def _tet_volumes(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    p = points[tets]
    return np.einsum("ij,ij->i", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0])) / 6.0


def build_model(
    points: np.ndarray,
    faces: np.ndarray,
    n_surface: int,
    material: ElasticMaterial,
    *,
    tets: np.ndarray | None = None,
    stretch: bool = True,
    bending: bool = True,
    volume: bool = True,
    tet_volume: bool = True,
    thickness: float | None = None,
    inflation: float = 1.0,
    stretch_compliance: float | None = None,
    bend_compliance: float | None = None,
    volume_compliance: float | None = None,
    tet_compliance: float | None = None,
    springs: np.ndarray | None = None,
    spring_compliance: float = 0.0,
    mass: float | None = None,
    closed: bool = True,
    name: str = "pbd",
) -> PbdModel:
    """Build a PBD model (see the module docstring for the physics of each choice).

    Args:
        points: (P, 3) rest positions [m]; the first ``n_surface`` are the vertices of ``faces``.
        faces: (M, 3) surface triangles (outward, counter-clockwise).
        n_surface: number of surface vertices.
        material: elastic material giving the compliances and density.
        tets: (T, 4) positively oriented tetrahedra over ``points``; enables tet edges and tet volumes.
        stretch, bending, volume, tet_volume: which constraint families to build.
        thickness: membrane/plate thickness h [m] of a surface-only body (default 5 % of the bounding-box diagonal).
        inflation: target enclosed volume as a multiple of the rest volume (balloons).
        *_compliance: override the material-derived compliance of a family with one value.
        springs: (S, 2) extra distance constraints (tethers, test springs) with ``spring_compliance`` [m/N].
        mass: total mass [kg], overriding rho times volume.
        closed: whether the surface is a closed, validated surface (needed for volume and surface mass).
        name: the body's name, for error messages.
    """
    points = np.asarray(points, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int32).reshape(-1, 3)
    n = points.shape[0]
    E, K = material.E, material.bulk_modulus
    diag = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0))) if n else 0.0
    h = 0.05 * diag if thickness is None else float(thickness)
    if not np.isfinite(h) or h <= 0.0:
        raise InvalidParameter(f"body '{name}': thickness = {thickness} m must be > 0")
    if not np.isfinite(inflation) or inflation <= 0.0:
        raise InvalidParameter(f"body '{name}': inflation = {inflation} must be > 0")
    if tets is not None:
        tets = np.asarray(tets, dtype=np.int32).reshape(-1, 4)
        if tets.size and (tets.min() < 0 or tets.max() >= n):
            raise InvalidMesh(f"body '{name}': tet indices must lie in [0, {n - 1}]")
    has_tets = tets is not None and len(tets) > 0
    rest_volume = wmesh.signed_volume(points[:n_surface], faces) if (closed and len(faces)) else 0.0
    if volume and not closed:
        raise InvalidMesh(f"body '{name}': the global volume constraint needs a closed surface (pass volume=False)")

    # masses
    if has_tets:
        vt = _tet_volumes(points, tets)
        if np.any(vt <= 0.0):
            bad = int(np.argmin(vt))
            raise InvalidMesh(f"body '{name}': tet {bad} has non-positive volume {vt[bad]:.3g} m^3 (inverted or degenerate)")
        m = np.zeros(n)
        np.add.at(m, tets.ravel(), np.repeat(material.rho * vt / 4.0, 4))
        unused = np.flatnonzero(m == 0.0)
        if unused.size:  # such a particle would have no mass and no stretch constraint: it would fall out
            raise InvalidMesh(
                f"body '{name}': {unused.size} particles belong to no tet (e.g. particle {unused[0]}); "
                "every surface vertex and interior point must be a tet corner"
            )
    elif closed and len(faces):
        a = wmesh.vertex_areas(points[:n_surface], faces)
        m = np.zeros(n)
        m[:n_surface] = material.rho * rest_volume * a / a.sum()
        if n > n_surface:
            raise InvalidParameter(f"body '{name}': interior particles need tets to get a mass")
    elif mass is not None:
        m = np.ones(n)
    else:
        raise InvalidParameter(f"body '{name}': an open surface or bare particle set needs mass= (total kg)")
    if mass is not None:
        if not np.isfinite(mass) or mass <= 0.0:
            raise InvalidParameter(f"body '{name}': mass = {mass} kg must be > 0")
        m = m * (float(mass) / m.sum())

    families: list[ConstraintFamily] = []

    # distance constraints: tet edges (tet body) or surface edges (surface body), plus user springs
    dist_idx = np.zeros((0, 2), dtype=np.int32)
    dist_alpha = np.zeros(0)
    if stretch:
        if has_tets:
            pairs = np.stack([tets[:, [0, 0, 0, 1, 1, 2]].ravel(), tets[:, [1, 2, 3, 2, 3, 3]].ravel()], axis=1)
            pairs = np.sort(pairs, axis=1)
            uniq, inverse = np.unique(pairs, axis=0, return_inverse=True)
            ve = np.zeros(len(uniq))
            np.add.at(ve, inverse.ravel(), np.repeat(vt / 6.0, 6))
            length = np.linalg.norm(points[uniq[:, 0]] - points[uniq[:, 1]], axis=1)
            alpha = length**2 / (_spring_modulus(material) * ve)
        else:
            uniq = wmesh.edges(faces)
            area = wmesh.face_areas(points, faces)
            fe = np.sort(np.stack([faces[:, [0, 1, 2]].ravel(), faces[:, [1, 2, 0]].ravel()], axis=1), axis=1)
            key_u = uniq[:, 0].astype(np.int64) * n + uniq[:, 1]
            key_f = fe[:, 0].astype(np.int64) * n + fe[:, 1]
            pos = np.searchsorted(key_u, key_f)
            ae = np.zeros(len(uniq))
            np.add.at(ae, pos, np.repeat(area / 3.0, 3))
            length = np.linalg.norm(points[uniq[:, 0]] - points[uniq[:, 1]], axis=1)
            alpha = length**2 / (E * h * ae)
        dist_idx = uniq.astype(np.int32)
        dist_alpha = _override(stretch_compliance, alpha, f"body '{name}': stretch_compliance")
    if springs is not None:
        s = np.asarray(springs, dtype=np.int32).reshape(-1, 2)
        if s.size and (s.min() < 0 or s.max() >= n or np.any(s[:, 0] == s[:, 1])):
            raise InvalidParameter(f"body '{name}': springs must join two different particles in [0, {n - 1}]")
        if not np.isfinite(spring_compliance) or spring_compliance < 0.0:
            raise InvalidParameter(f"body '{name}': spring_compliance = {spring_compliance} m/N must be >= 0")
        dist_idx = np.concatenate([dist_idx, s])
        dist_alpha = np.concatenate([dist_alpha, np.full(len(s), float(spring_compliance))])
    if len(dist_idx):
        rest = np.linalg.norm(points[dist_idx[:, 0]] - points[dist_idx[:, 1]], axis=1)
        families.append(_family("distance", dist_idx, rest, dist_alpha, n))

    if bending and len(faces):
        hg = wmesh.hinges(faces)
        if len(hg):
            w1, w2, e0, e1 = (points[hg[:, k]] for k in range(4))
            E_vec = e1 - e0
            n1 = np.cross(E_vec, w1 - e0)
            n2 = np.cross(e0 - e1, w2 - e1)
            n1h = n1 / np.linalg.norm(n1, axis=1, keepdims=True)
            n2h = n2 / np.linalg.norm(n2, axis=1, keepdims=True)
            eh = E_vec / np.linalg.norm(E_vec, axis=1, keepdims=True)
            theta0 = np.arctan2(np.einsum("ij,ij->i", np.cross(n1h, n2h), eh), np.einsum("ij,ij->i", n1h, n2h))
            D = E * h**3 / (12.0 * (1.0 - material.nu**2))
            a12 = 0.5 * (np.linalg.norm(n1, axis=1) + np.linalg.norm(n2, axis=1))
            alpha = a12 / (D * np.einsum("ij,ij->i", E_vec, E_vec))
            alpha = _override(bend_compliance, alpha, f"body '{name}': bend_compliance")
            families.append(_family("bending", hg.astype(np.int32), theta0, alpha, n))

    if has_tets and tet_volume:
        lam_vol = _volume_modulus(material)
        if lam_vol > 0.0 or tet_compliance is not None:
            alpha = vt / lam_vol if np.isfinite(lam_vol) and lam_vol > 0.0 else np.zeros(len(vt))
            alpha = _override(tet_compliance, alpha, f"body '{name}': tet_compliance")
            families.append(_family("tet_volume", tets, vt, alpha, n))

    vol = None
    if volume:
        alpha_v = rest_volume / K if np.isfinite(K) else 0.0
        if volume_compliance is not None:
            alpha_v = float(_override(volume_compliance, np.zeros(1), f"body '{name}': volume_compliance")[0])
        corner_v = faces.ravel().astype(np.int64)
        order = np.argsort(corner_v, kind="stable")
        start = np.concatenate([[0], np.cumsum(np.bincount(corner_v, minlength=n))]).astype(np.int32)
        vol = GlobalVolume(
            rest_volume=rest_volume,
            target_volume=inflation * rest_volume,
            compliance=alpha_v,
            vertex_face_start=start,
            vertex_faces=(order // 3).astype(np.int32),
        )

    return PbdModel(
        rest_points=np.ascontiguousarray(points),
        faces=np.ascontiguousarray(faces),
        n_surface=int(n_surface),
        mass=m,
        families=tuple(families),
        volume=vol,
    )
