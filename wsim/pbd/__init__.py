"""Position-based dynamics (XPBD) bodies."""

from wsim.pbd.body import PbdBody
from wsim.pbd.model import ConstraintFamily, PbdModel, build_model

__all__ = ["PbdBody", "PbdModel", "ConstraintFamily", "build_model"]
