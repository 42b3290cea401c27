"""The named causes of ``cellcal analyze`` (ids as in the project's causes vocabulary)."""
from cellcal.solvers.analysis.effects.backlash import Backlash
from cellcal.solvers.analysis.effects.base import Cause, Context, JointBasis, Term, approach_directions
from cellcal.solvers.analysis.effects.cyclic_joint_error import CyclicJointError
from cellcal.solvers.analysis.effects.joint_compliance import JointCompliance
from cellcal.solvers.analysis.effects.parallel_axis_tilt import ParallelAxisTilt
from cellcal.solvers.analysis.effects.thermal_drift import ThermalDrift
from cellcal.solvers.analysis.effects.trigger_latency import TriggerLatency

CAUSES: dict[str, Cause] = {c.id: c for c in (JointCompliance(), Backlash(), ThermalDrift(), CyclicJointError(),
                                              ParallelAxisTilt(), TriggerLatency())}
IDS = ("none", *CAUSES)

__all__ = ["CAUSES", "IDS", "Cause", "Context", "JointBasis", "Term", "approach_directions"]
