"""The exceptions a wsim user sees.

Every error names the object (body, collider, mesh, file) and the quantity that is wrong, so a
scene script fails with a message that says what to fix.
"""

from __future__ import annotations


class WsimError(Exception):
    """Base class of every error wsim raises on purpose."""


class InvalidMesh(WsimError, ValueError):
    """A mesh cannot be used by the method that was given it (open, degenerate, mis-oriented...)."""


class InvalidMaterial(WsimError, ValueError):
    """A material parameter is outside its physical range (E <= 0, rho <= 0, nu outside (-1, 0.5))."""


class InvalidParameter(WsimError, ValueError):
    """A simulation parameter is out of range (dt <= 0, fps <= 0, substeps < 1, ...)."""


class OutputError(WsimError, OSError):
    """An output file cannot be written; raised before any simulation work is done."""


class SimulationDiverged(WsimError, RuntimeError):
    """A step produced NaN or Inf (or, with ``reason``, another sign of divergence such as a
    displacement beyond a body's ``divergence_limit``).

    Attributes:
        body: name of the body whose state went non-finite.
        step: the frame index at whose end the check failed.
        quantity: which state array held the first non-finite value ("positions", "velocities"...).
        time: simulation time [s] at the end of that frame.
    """

    def __init__(self, body: str, step: int, quantity: str, time: float, detail: str = "",
                 reason: str = "non-finite") -> None:
        self.body = body
        self.step = step
        self.quantity = quantity
        self.time = time
        msg = f"body '{body}': {reason} {quantity} at frame {step} (t = {time:.6g} s)"
        if detail:
            msg += f"; {detail}"
        super().__init__(msg)


class CheckpointError(WsimError, ValueError):
    """A checkpoint cannot be restored: unreadable (truncated, not a wsim checkpoint), another format
    version, or saved from another scene. The World it was loaded into is left unchanged."""
