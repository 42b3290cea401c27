"""The named causes of ``cellcal analyze`` (ids as in the project's causes vocabulary)."""
from .backlash import Backlash
from .base import Cause, Context, JointBasis, Term, approach_directions
from .cyclic_joint_error import CyclicJointError
from .joint_compliance import JointCompliance
from .parallel_axis_tilt import ParallelAxisTilt
from .thermal_drift import ThermalDrift
from .trigger_latency import TriggerLatency

CAUSES: dict[str, Cause] = {c.id: c for c in (JointCompliance(), Backlash(), ThermalDrift(), CyclicJointError(),
                                              ParallelAxisTilt(), TriggerLatency())}
IDS = ("none", *CAUSES)

__all__ = ["CAUSES", "IDS", "Cause", "Context", "JointBasis", "Term", "approach_directions"]
