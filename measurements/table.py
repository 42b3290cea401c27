"""The measurement CSV that ``cellcal identify`` and ``cellcal analyze`` read.

One header line, then one row per measurement in the order measured; comma
separated, ``.`` as decimal point, UTF-8. Lines whose first character is ``#``
are comments and blank lines are skipped; line numbers in messages are physical
lines of the file. Each record is one physical line.

Required: ``q1_deg`` .. ``qN_deg`` or ``q1_rad`` .. ``qN_rad`` (one unit for all
joints, N = the robot model's joint count) and ``x_mm``, ``y_mm``, ``z_mm``.
Optional: ``target``, ``qw``/``qx``/``qy``/``qz`` (all four or none), ``t_s``,
``temp_c``, ``payload_kg``, ``split`` (``cal`` or ``val``). Other columns are
kept as text.

The point form (calibration from the cell's own fixtures): a ``point`` column names the
unknown fixed point the target sat at (a socket) or touched (a stylus) instead of a
measured position, with an optional ``setup`` (one placement of the fixture; the same
point id in two setups is two points). A row then has either a point or ``x_mm``,
``y_mm``, ``z_mm``, never both; the position columns may be left out when every row has
a point. Point rows carry NaN positions in ``xyz_mm``; ``observations()`` refuses them.

A file that cannot be used raises :class:`DatasetError` with one message naming the
file, the line and the column; nothing is partly loaded. Here are the format's columns and
limits and the table of rows; :mod:`.reader` reads a file, :mod:`.writer` writes one.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, fields

import numpy as np

from cellcal.solvers.identification.measurement_model import Observations

XYZ = ("x_mm", "y_mm", "z_mm")
QUAT = ("qw", "qx", "qy", "qz")
SCALARS = ("t_s", "temp_c", "payload_kg")
SPLITS = ("cal", "val")
DEFAULT_TARGET = "tcp"
POINT_COLS = ("point", "setup")
DEFAULT_SETUP = "default"  # the setup of point rows in a file without a setup column (or an empty cell)
KNOWN = XYZ + QUAT + SCALARS + ("target", "split") + POINT_COLS

MAX_POSITION_MM = 1e5  # 100 m: beyond any tracker's range
MAX_JOINT = {"rad": 4 * np.pi, "deg": 720.0}  # two turns either way
MAX_PAYLOAD_KG = 2500.0  # the heaviest industrial arms carry about 2.3 t

JOINT_COLUMN = re.compile(r"q(\d+)_(deg|rad)")


class DatasetError(ValueError):
    """A measurement file that cannot be used; the message names file, line and column."""


@dataclass(frozen=True)
class MeasurementTable:
    """The rows of one measurement file, in measurement order."""

    path: str
    q_rad: np.ndarray  # (N, n_joints)
    xyz_mm: np.ndarray  # (N, 3), instrument frame
    target: np.ndarray  # (N,) int index into target_names
    target_names: tuple[str, ...]  # order of first appearance
    line: np.ndarray  # (N,) 1-based physical line of each row
    quat: np.ndarray | None  # (N, 4) qw, qx, qy, qz, unit norm
    t_s: np.ndarray | None
    temp_c: np.ndarray | None
    payload_kg: np.ndarray | None
    split: np.ndarray | None  # (N,) 'cal' or 'val'
    extra: dict[str, tuple[str, ...]]  # unknown columns, as text
    joint_unit: str  # 'deg' or 'rad', as in the file
    # point form: the fixed point of each row ('' on a row with a measured position) and its setup
    point: np.ndarray | None = None  # (N,) str, or None when the file has no point column
    setup: np.ndarray | None = None  # (N,) str, DEFAULT_SETUP where none was given; '' on position rows

    @property
    def is_point(self) -> np.ndarray:
        """(N,) bool: rows of the point form (a fixed point, no measured position)."""
        return np.zeros(len(self), bool) if self.point is None else self.point != ""

    def __len__(self) -> int:
        return len(self.q_rad)

    def rows(self, mask_or_indices) -> "MeasurementTable":
        """The subset of rows picked by a boolean mask or indices; target_names is kept whole."""
        idx = np.asarray(mask_or_indices)
        idx = np.flatnonzero(idx) if idx.dtype == bool else idx.astype(int).reshape(-1)
        picked = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, np.ndarray):
                value = value[idx]
            elif f.name == "extra":
                value = {k: tuple(v[i] for i in idx) for k, v in value.items()}
            picked[f.name] = value
        return MeasurementTable(**picked)

    def observations(self) -> Observations:
        """The rows as measured positions; a point-form row has none, and is refused here."""
        points = np.flatnonzero(self.is_point)
        if points.size:
            raise DatasetError(
                f"{self.path}:{self.line[points[0]]}: column 'point': {counted_rows(points.size)} of the point form "
                "(a fixed point, no measured position); this command needs x_mm, y_mm, z_mm in every row (point-form "
                "data are read by cellcal identify, with --fixture for the fixture's distances)")
        return Observations(q=self.q_rad, xyz_mm=self.xyz_mm, target=self.target, target_names=self.target_names)


def counted_rows(n: int) -> str:
    return f"{n} row" if n == 1 else f"{n} rows"


def check_joint_limits(table: MeasurementTable, joint_limits, model_name: str) -> None:
    """Refuse joint values outside the robot model's limits, naming the column and rows
    (degrees under a ``_rad`` header end up here)."""
    if joint_limits is None:
        return
    unit = table.joint_unit
    scale = np.rad2deg(1.0) if unit == "deg" else 1.0
    margin = np.deg2rad(1.0)  # a controller reports a joint a hair past its software limit
    for j, (lo, hi) in enumerate(np.asarray(joint_limits)):
        outside = np.flatnonzero((table.q_rad[:, j] < lo - margin) | (table.q_rad[:, j] > hi + margin))
        if outside.size:
            lines = ", ".join(str(n) for n in table.line[outside[:5]]) + (" ..." if outside.size > 5 else "")
            hint = " (degrees under a _rad header?)" if unit == "rad" and np.abs(table.q_rad).max() > 2 * np.pi \
                else ""
            raise DatasetError(
                f"{table.path}: column 'q{j + 1}_{unit}': {outside.size} of {len(table)} rows "
                f"{'is' if outside.size == 1 else 'are'} outside {model_name}'s joint {j + 1} limits "
                f"{lo * scale:g}..{hi * scale:g} {unit}{hint}; line{'' if outside.size == 1 else 's'} {lines}")


def repeated_measurements(table: MeasurementTable) -> list[tuple[int, int]]:
    """Rows that repeat an earlier row's joints, target and measured position exactly, as (line of the
    first, line of the repeat) pairs in file order. No instrument measures the same position twice to
    the last digit, so these are copies: fits and spreads then count one measurement as two, and every
    standard deviation computed from the data comes out too small."""
    key = np.column_stack([table.q_rad, np.nan_to_num(table.xyz_mm), table.target])
    if table.point is not None:  # point rows: the same joints at the same point of the same setup
        _, point_id = np.unique(np.char.add(np.char.add(table.setup, "\0"), table.point), return_inverse=True)
        key = np.column_stack([key, point_id.reshape(-1)])
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    return [(int(table.line[first[g]]), int(table.line[k])) for k, g in enumerate(inverse) if first[g] != k]


def repeated_warning(table: MeasurementTable) -> str | None:
    """One line on :func:`repeated_measurements` for a command's stderr, or None when there are none."""
    repeated = repeated_measurements(table)
    if not repeated:
        return None
    first, again = repeated[0]
    return (f"{table.path}: {len(repeated)} of {len(table)} rows repeat an earlier row exactly (line {again} is line "
            f"{first} again): copies, not measurements; the standard deviations and standard errors reported come "
            "out too small")


# Two rows are the same pose when every joint agrees within this: a pose read again reads its joints to
# the encoders' noise (about 1e-5 rad on a UR), while two poses of a calibration plan differ by degrees.
SAME_POSE_RAD = 1e-4


def overlap_rows(cal: MeasurementTable, val: MeasurementTable) -> int:
    """How many rows of `val` are a pose `cal` has too: the same target name (and, on point rows, the
    same point of the same setup) at joints within SAME_POSE_RAD of a calibration row. A validation on
    such rows scores the fit on its own data."""
    from scipy.spatial import cKDTree

    def keys(table: MeasurementTable) -> np.ndarray:
        names = np.array(table.target_names, dtype=object)[table.target].astype(str)
        if table.point is not None:
            names = np.char.add(np.char.add(np.char.add(names, "\0"), table.setup.astype(str)),
                                np.char.add("\0", table.point.astype(str)))
        return names

    cal_keys, val_keys = keys(cal), keys(val)
    count = 0
    for key in np.unique(val_keys):
        ours = cal.q_rad[cal_keys == key]
        if not len(ours):
            continue
        theirs = val.q_rad[val_keys == key]
        distance, _ = cKDTree(ours).query(theirs, p=np.inf)
        count += int(np.count_nonzero(distance <= SAME_POSE_RAD))
    return count


def overlap_warning(cal: MeasurementTable, val: MeasurementTable, overlap: int) -> str | None:
    """One line for stderr when validation rows are calibration rows, or None; a validation that is
    mostly overlap is said to be no validation."""
    if overlap == 0:
        return None
    most = 2 * overlap > len(val)
    return (f"{val.path}: {overlap} of {len(val)} validation rows are poses the calibration rows of {cal.path} "
            f"have too (same target, joints within {SAME_POSE_RAD:g} rad): "
            + ("this is mostly the calibration's own data, not a validation; its score says how well the fit "
               "fits, not how well it predicts" if most else "their part of the score is in-sample"))

