"""Writing the measurement CSV (the format: :mod:`.table`) so that :mod:`.reader` takes it
back bit for bit: floats as their shortest exact repr, one record per line."""
from __future__ import annotations

import csv
import os

import numpy as np

from cellcal.measurements.table import DEFAULT_TARGET, JOINT_COLUMN, KNOWN, QUAT, SPLITS, XYZ, MeasurementTable


def write_measurements(path, *, q_rad, xyz_mm, target_names=None, target=None, t_s=None, temp_c=None,
                       payload_kg=None, split=None, quat=None, extra=None, comment: str | None = None,
                       joint_unit: str = "rad", point=None, setup=None) -> None:
    """Write measurements in the format :func:`read_measurements` reads; floats round-trip exactly.

    point (and setup): the point form, one id per row ('' on a row with a measured position); the
    position cells of point rows are left empty (their xyz_mm may be NaN)."""
    q = np.atleast_2d(np.asarray(q_rad, dtype=float))
    n = len(q)
    if joint_unit not in ("deg", "rad"):
        raise ValueError(f"joint_unit must be 'deg' or 'rad', got {joint_unit!r}")
    columns: dict[str, list[str]] = {}

    def numeric(names, values, width):
        a = np.asarray(values, dtype=float).reshape(n, width)
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{', '.join(names)}: values must be finite")
        for j, c in enumerate(names):
            columns[c] = [repr(float(v)) for v in a[:, j]]

    q_out = np.rad2deg(q) if joint_unit == "deg" else q
    numeric([f"q{k}_{joint_unit}" for k in range(1, q.shape[1] + 1)], q_out, q.shape[1])
    if point is None:
        numeric(XYZ, xyz_mm, 3)
    else:
        ids = [str(v).strip() for v in np.asarray(point, dtype=object).reshape(n)]
        where = np.array([v != "" for v in ids], dtype=bool)
        xyz = np.asarray(xyz_mm, dtype=float).reshape(n, 3) if xyz_mm is not None else np.full((n, 3), np.nan)
        if not np.all(np.isfinite(xyz[~where])):
            raise ValueError("x_mm, y_mm, z_mm: values must be finite on rows without a point")
        if (~where).any():
            for j, c in enumerate(XYZ):
                columns[c] = ["" if w else repr(float(v)) for v, w in zip(xyz[:, j], where)]
        columns["point"] = ids
        if setup is not None:
            sets = [str(v).strip() for v in np.asarray(setup, dtype=object).reshape(n)]
            columns["setup"] = [v if w else "" for v, w in zip(sets, where)]
    if target is not None:
        names = tuple(target_names) if target_names is not None else None
        if not names or any(not str(t).strip() for t in names):
            raise ValueError("target needs target_names, each a non-empty id")
        columns["target"] = [str(names[i]).strip() for i in np.asarray(target, dtype=int).reshape(n)]
    if quat is not None:
        quat = np.asarray(quat, dtype=float).reshape(n, 4)
        if np.any(np.linalg.norm(quat, axis=1) < 1e-9):
            raise ValueError("quat: zero-norm quaternion")
        numeric(QUAT, quat, 4)
    for c, values in (("t_s", t_s), ("temp_c", temp_c), ("payload_kg", payload_kg)):
        if values is not None:
            numeric([c], values, 1)
    if split is not None:
        columns["split"] = [str(s) for s in np.asarray(split).reshape(n)]
        if not set(columns["split"]) <= set(SPLITS):
            raise ValueError("split values must be 'cal' or 'val'")
    for c, values in (extra or {}).items():
        if c in columns or c in KNOWN or JOINT_COLUMN.fullmatch(c):
            raise ValueError(f"extra column {c!r} clashes with a column of the format")
        columns[c] = [str(v) for v in values]
        if len(columns[c]) != n:
            raise ValueError(f"extra column {c!r} has {len(columns[c])} values for {n} rows")

    for c in ("target", "point", "setup", *(extra or {})):
        if any("\n" in v or "\r" in v for v in columns.get(c, ())):
            raise ValueError(f"column {c!r}: values must not contain line breaks (one record per line)")
    with open(os.fspath(path), "w", encoding="utf-8", newline="") as f:
        for text in (comment.splitlines() if comment else ()):
            f.write(f"# {text}\n")
        out = csv.writer(f, lineterminator="\n")
        out.writerow(columns)
        out.writerows(zip(*columns.values()))


def write_table(path, table: MeasurementTable, comment: str | None = None) -> None:
    """Write a MeasurementTable; the target column is left out for a single default target."""
    single = table.target_names == (DEFAULT_TARGET,)
    write_measurements(
        path, q_rad=table.q_rad, xyz_mm=table.xyz_mm, target_names=table.target_names,
        target=None if single else table.target, t_s=table.t_s, temp_c=table.temp_c,
        payload_kg=table.payload_kg, split=table.split, quat=table.quat, extra=table.extra,
        comment=comment, joint_unit=table.joint_unit, point=table.point, setup=table.setup,
    )
