"""What a routine's tool frame is made of: what the routine determined, and, for the rest,
the controller's tool frame from before the run.

A routine writes only what it determined (:attr:`~.base.Result.determines`): ``tip`` (the
TCP's position in the flange frame) and/or ``axis`` (the direction of the tool frame's z).
No routine here determines the turn of the frame about the tool's axis (a round tool has
none to measure). Everything else is kept from the *reference*: the controller's tool frame
from before the run (``tool_frame_before`` in the dataset's meta, recorded by
:mod:`.runner`), so a calibration made earlier is not undone by a routine that did not
measure it:

* tip only (``tcp-npoint``): the position is the routine's, the whole orientation the
  reference's;
* axis only (``tcf``): the position is the reference's; the orientation is the reference's
  turned by the smallest rotation that takes its z onto the measured axis
  (:func:`cellcal.solvers.geometry.se3.with_z_axis`), so its turn about the axis is kept too;
* tip and axis (``tcp-laser``, ``tcp-stylus``): the position is the routine's, the
  orientation as for axis only.

Where no controller frame is known (a dataset recorded without one, or a controller whose
tool frame is all zero: the bare flange, never a tool's calibration), the reference is the
tool as drawn, with what the routine's section of the cell file states in its place (a
``tcp_mm`` or ``tool_axis`` option), and the result's notes say so.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from cellcal.solvers.geometry import se3

TIP = "tip"
AXIS = "axis"
TIP_ONLY = frozenset({TIP})
AXIS_ONLY = frozenset({AXIS})
TIP_AND_AXIS = frozenset({TIP, AXIS})
NOTHING = frozenset()


def described(determines) -> str:
    """``the tip and the axis``, ``the tip only``, ``the axis only`` or ``no tool frame``."""
    determines = frozenset(determines)
    if determines == TIP_AND_AXIS:
        return "the tip and the axis"
    if determines == TIP_ONLY:
        return "the tip only"
    if determines == AXIS_ONLY:
        return "the axis only"
    return "no tool frame"


@dataclass(frozen=True)
class Reference:
    """The tool frame a result keeps what it did not determine from.

    ``pose`` [x, y, z, rx, ry, rz] (m, rad); ``source`` says in words where it comes from;
    ``from_controller`` is True when it is the controller's frame from before the run;
    ``notes`` say what of the cell file was used or passed over, and why."""

    pose: np.ndarray
    source: str
    from_controller: bool
    notes: tuple[str, ...] = field(default=())

    @property
    def axis(self) -> np.ndarray:
        """The reference's tool axis (its z) in the flange frame."""
        return se3.rotvec_to_matrix(self.pose[3:])[:, 2]


def controller_frame(before) -> np.ndarray | None:
    """The controller's tool frame from before the run, or None where none is known: no
    record of it, or all zero (the bare flange: no tool's frame)."""
    if before is None:
        return None
    pose = np.asarray(before, dtype=float).reshape(-1)
    if pose.shape != (6,) or not np.all(np.isfinite(pose)) or not np.any(pose):
        return None
    return pose


def reference(before, drawn_pose, *, tip_m=None, tip_option: str = "", axis=None, axis_option: str = "") -> Reference:
    """The reference for a result: the controller's frame from before the run (`before`,
    the dataset's ``tool_frame_before``) when known, else the tool as drawn (`drawn_pose`),
    its tip replaced by `tip_m` and its axis turned onto `axis` where the routine's section of
    the cell file states them (`tip_option` / `axis_option` name the option). A stated option
    is passed over, with a note, when the controller's frame is known: that frame is the newer
    statement (a later calibration), and a cell file's option must not undo it."""
    pose = controller_frame(before)
    if pose is not None:
        notes = []
        if tip_m is not None:
            off = float(np.linalg.norm(pose[:3] - np.asarray(tip_m, dtype=float)) * 1e3)
            notes.append(f"{tip_option} is not used ({off:.3f} mm from the controller's TCP): the controller's tool "
                         "frame from before the run is known and is the newer statement")
        if axis is not None:
            u = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
            off = float(np.degrees(np.arccos(np.clip(se3.rotvec_to_matrix(pose[3:])[:, 2] @ u, -1.0, 1.0))))
            notes.append(f"{axis_option} is not used ({off:.4f} deg from the controller's tool axis): the "
                         "controller's tool frame from before the run is known and is the newer statement")
        return Reference(pose, "the controller's tool frame from before the run", True, tuple(notes))
    pose = np.array(drawn_pose, dtype=float)
    stated_parts = []
    if tip_m is not None:
        pose[:3] = np.asarray(tip_m, dtype=float)
        stated_parts.append(f"its TCP from {tip_option}")
    if axis is not None:
        pose[3:] = se3.with_z_axis(pose[3:], axis)
        stated_parts.append(f"its axis from {axis_option}")
    source = "the tool as drawn ([tool])" + (f", with {' and '.join(stated_parts)}" if stated_parts else "")
    note = (f"no tool frame of the controller's from before the run is known (not recorded with the dataset, or "
            f"all zero: the bare flange): what this routine does not determine is taken from {source}")
    return Reference(pose, source, False, (note,))


def compose(determines, ref: Reference, *, tip_m=None, axis=None) -> tuple[np.ndarray, list[str]]:
    """The tool frame to write [x, y, z, rx, ry, rz] (m, rad) and the notes that say what in
    it was kept from `ref`. `determines` is a subset of {TIP, AXIS}: `tip_m` (flange frame,
    m) is given with TIP, the unit `axis` (flange frame) with AXIS."""
    determines = frozenset(determines)
    if not determines or not determines <= TIP_AND_AXIS:
        raise ValueError(f"a tool frame needs the tip or the axis determined, not {sorted(determines)}")
    if (TIP in determines) != (tip_m is not None) or (AXIS in determines) != (axis is not None):
        raise ValueError("give the tip exactly when it is determined, and the axis exactly when it is")
    position = np.asarray(tip_m, dtype=float) if TIP in determines else ref.pose[:3].copy()
    rotvec = se3.with_z_axis(ref.pose[3:], axis) if AXIS in determines else ref.pose[3:].copy()
    if determines == TIP_ONLY:
        kept = (f"this routine determines the tip only: the tool frame keeps the orientation of {ref.source} "
                "(its axis and its turn about the axis)")
    elif determines == AXIS_ONLY:
        kept = (f"this routine determines the axis only: the tool frame keeps the TCP position of {ref.source}, "
                "and its orientation turned by the smallest rotation that takes its z onto the measured axis (the "
                "turn about the axis is kept)")
    else:
        kept = (f"the turn of the tool frame about the tool axis is not measured (a round tool has none): it is kept "
                f"from {ref.source}, whose orientation is turned by the smallest rotation that takes its z onto the "
                "measured axis")
    return np.concatenate([position, rotvec]), [kept, *ref.notes]



def change(new, old, determines=TIP_AND_AXIS) -> dict:
    """The change of a tool frame as the panel's outcome registers carry it: the tip's
    x, y, z (mm) and the z axis' lean toward x and y (deg), both in the flange frame, new
    minus old; None for what `determines` leaves out (daemon/outcome.py)."""
    new, old = np.asarray(new, dtype=float), np.asarray(old, dtype=float)
    tip = (new[:3] - old[:3]) * 1e3 if TIP in determines else [None] * 3
    if AXIS in determines:
        lean = np.degrees(np.subtract(se3.z_axis_lean(new[3:]), se3.z_axis_lean(old[3:])))
    else:
        lean = [None, None]
    values = [*tip, *lean]
    return {k: None if v is None else float(v)
            for k, v in zip(("x_mm", "y_mm", "z_mm", "tilt_x_deg", "tilt_y_deg"), values)}
