"""``EolState``: everything of an ``EolBody`` that changes when it steps (see ``wsim.state``).

Beside it the body keeps what never changes after ``bind`` (the grid, the material points and
surface in the material domain, contact samples) and what each step recomputes (forces, lumped
masses and elastic energy: derived from the state by the force pass; scratch buffers).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import warp as wp


@dataclass
class EolState:
    """The state of one EoL body. Device arrays (``wp.array``) on the body's device; the rest on the host.

    Attributes:
        z: (n_nodes,) vec3d reference map z(y) at the grid nodes [m] (advected).
        v: (n_nodes,) vec3d Eulerian velocity v at the nodes [m/s] (velocity axes, see ``eol_step``).
        y_points: (P,) vec3d material points found in the intermediate domain (Algorithm 2; the
            next step's Newton guesses) [m].
        y_vertices: (V,) vec3d surface vertices in the intermediate domain (likewise) [m].
        Fp_inv: (P,) mat33d plastic F_p^-1 per material point ((1,) identity placeholder without plasticity).
        F: (3, 3) Lagrangian deformation gradient F_L (R rigid, A affine, I Eulerian).
        T: (3,) Lagrangian translation [m] (x = F y + T).
        Tdot: (3,) world velocity of the frame origin [m/s].
        omega: (3,) rigid angular velocity in body axes [rad/s].
        Adot: (3, 3) affine dA/dt [1/s].
        dt_prev: the last step's dt [s] (the next dt guess of the contact QP).
        time: the body's time [s].  steps: steps taken.
        active_rows: ids of the contact rows active in the last QP (its warm start; variable length),
            with those of the rows between it and other EoL bodies that it keeps (``wsim.eol.pairs``).
        contact_impulse, gravity_impulse, load_impulse: (3,) momentum delivered by contact, by gravity and
            by the loads (``add_traction``, ``add_body_force``) so far [kg m/s].
        coupling_force, coupling_until, coupling_impulse: the point forces [N] (V, 3) of
            ``add_vertex_impulses`` still being delivered, until when [s] (-1: none), and the momentum
            handed over so far [N s].
        partner_push: (n, 4) the normal push this body handed each yielding moving surface over the
            last coupling interval, per vertex: the surface's key, then the impulse [N s] (world);
            the partner takes it over the next interval (``EolBody.set_moving_surfaces``).
        grid_grown: (6,) cells the grid has grown by since ``bind``, below x, y, z and above x, y, z
            (``EolBody._regrid``; z and v are sized by the grown grid).
        failure: utf-8 bytes of "quantity\\x1fdetail\\x1freason" once a step failed (empty: none).
    """

    _ragged: ClassVar[tuple[str, ...]] = ("active_rows", "failure", "coupling_force", "partner_push")

    z: wp.array
    v: wp.array
    y_points: wp.array
    y_vertices: wp.array
    Fp_inv: wp.array
    F: np.ndarray
    T: np.ndarray
    Tdot: np.ndarray
    omega: np.ndarray
    Adot: np.ndarray
    dt_prev: float
    time: float = 0.0
    steps: int = 0
    active_rows: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    contact_impulse: np.ndarray = field(default_factory=lambda: np.zeros(3))
    gravity_impulse: np.ndarray = field(default_factory=lambda: np.zeros(3))
    load_impulse: np.ndarray = field(default_factory=lambda: np.zeros(3))
    grid_grown: np.ndarray = field(default_factory=lambda: np.zeros(6, dtype=np.int64))
    coupling_force: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    coupling_until: float = -1.0
    coupling_impulse: np.ndarray = field(default_factory=lambda: np.zeros(3))
    partner_push: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    failure: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.uint8))

    def get_failure(self) -> tuple[str, str, str] | None:
        """(quantity, detail, reason) of the failure, or None."""
        if len(self.failure) == 0:
            return None
        q, d, r = bytes(self.failure).decode("utf-8").split("\x1f")
        return q, d, r

    def set_failure(self, failure: tuple[str, str, str] | None) -> None:
        self.failure = (np.zeros(0, dtype=np.uint8) if failure is None
                        else np.frombuffer("\x1f".join(failure).encode("utf-8"), dtype=np.uint8).copy())
