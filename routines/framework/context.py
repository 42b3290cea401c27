"""What one run knows from its start, read once and carried to every step.

A run reads each fact once: the routine's section of the cell file (its options), robot a's
model file, the controller's tool frame before anything moves, and what earlier runs found
(the beams a tcp-laser calibration located). The service builds a :class:`RunContext` when it
has checked that the run may start; ``cellcal run`` and the offline solve build one from the
cell file alone (:func:`.runner.offline_context`). Planning, the guard, the routine's measuring
and solving, and the write of the tool frame all take what they need from it, so two parts of
one run cannot disagree about a fact.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cellcal.config.cells import Cell


@dataclass(frozen=True)
class BeamPoint:
    """Where a beam of ``[beams]`` passes (base frame, m): as a calibration found it, or as a
    routine's section states it. Its direction and width stay those of ``[beams]``."""

    channel: int
    point_m: np.ndarray  # (3,)


@dataclass(frozen=True)
class RunContext:
    """One run's facts, read once at its start (immutable).

    ``options``: the routine's section of the cell file, read and bounded (with what earlier
    runs found merged in: :meth:`~.base.Routine.with_history`); ``robot_model``: robot a's
    kinematic model; ``tool_frame_before``: the controller's tool frame (flange -> TCP, m, rad)
    before the run, None where it is not known yet (a run from the cell file alone reads it when
    it starts to move); ``history_note``: what was taken from earlier runs, or None."""

    routine: str
    cell: Cell
    options: object
    robot_model: object  # cellcal.solvers.geometry KinematicModel
    run_id: int | None = None
    tool_id: int = 0
    tool_frame_before: np.ndarray | None = None
    history_note: str | None = None

    @property
    def beams(self) -> tuple[BeamPoint, ...]:
        """The beams the run measures against where they are known better than ``[beams]`` as
        installed (a calibration found them, or the routine's section states them), in metres;
        () when the run measures against ``[beams]`` as installed."""
        return tuple(getattr(self.options, "beams", ()) or ())
