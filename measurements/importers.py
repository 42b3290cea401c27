"""Vendor and data-set exports to the measurement CSV (``cellcal import``).

A small registry: each importer is a function (source path) -> MeasurementTable
fields, registered under a format name; new formats join with :func:`register`.
"""
from __future__ import annotations

import csv
import re
from pathlib import Path
from typing import Callable

import numpy as np

from cellcal.measurements.table import DatasetError

IMPORTERS: dict[str, tuple[Callable, str]] = {}
_NUMBERS = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")


def register(name: str, description: str):
    def wrap(fn):
        IMPORTERS[name] = (fn, description)
        return fn
    return wrap


def _floats(path, record, column, text, count):
    values = [float(v) for v in _NUMBERS.findall(text)]
    if len(values) != count or not np.all(np.isfinite(values)):
        raise DatasetError(f"{path}: record {record}: column {column!r}: expected {count} numbers, "
                           f"got {len(values)}")
    return values


@register("dlr-justin", "DLR Agile Justin calibration data (index, joints [19 rad], markers [[right],[left]] m)")
def dlr_justin(path: Path) -> dict:
    """Two rows per measurement (targets right, left), joints in rad, markers m -> mm."""
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            records = list(csv.reader(fh))
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: cannot read: {exc}") from None
    if not records or [c.strip() for c in records[0]] != ["", "joints", "markers"]:
        raise DatasetError(f"{path}: header must be ',joints,markers' (the DLR export), got {records[:1]}")
    q, xyz, target = [], [], []
    for i, rec in enumerate(records[1:], start=1):
        if len(rec) != 3:
            raise DatasetError(f"{path}: record {i}: expected 3 fields, got {len(rec)}")
        joints = _floats(path, i, "joints", rec[1], 19)
        markers = np.array(_floats(path, i, "markers", rec[2], 6)).reshape(2, 3) * 1000.0
        for t, name in enumerate(("right", "left")):
            q.append(joints)
            xyz.append(markers[t])
            target.append(t)
    if not q:
        raise DatasetError(f"{path}: no measurements")
    return {"q_rad": np.array(q), "xyz_mm": np.array(xyz), "target_names": ("right", "left"),
            "target": np.array(target)}


_MUKCA_POINT = re.compile(r"hole_\d+")


def _mukca_placement(folder: Path) -> list[tuple[str, np.ndarray]]:
    """One placement folder: (point id, joint rows) per ``hole_<k>.csv`` (the ``hole_<k>_pose.csv`` side files
    are not measurements and are left out)."""
    out = []
    for path in sorted(folder.glob("hole_*.csv")):
        if not _MUKCA_POINT.fullmatch(path.stem):
            continue
        try:
            lines = path.read_text(encoding="utf-8").splitlines()
        except (OSError, UnicodeDecodeError) as exc:
            raise DatasetError(f"{path}: cannot read: {exc}") from None
        rows = [_floats(path, i, "joints", line, 7) for i, line in enumerate(lines, start=1) if line.strip()]
        if not rows:
            raise DatasetError(f"{path}: no rows")
        out.append((path.stem, np.array(rows)))
    return out


@register("mukca", "socket-plate seatings, one folder per placement of hole_<k>.csv (7 joints, rad, no header); "
                   "SOURCE a placement folder or a folder of them; setup = the placement folder's name")
def mukca(path: Path) -> dict:
    """The point form: one row per seating, point = the file's ``hole_<k>``, setup = its placement folder."""
    if not path.is_dir():
        raise DatasetError(f"{path}: expected a folder of hole_<k>.csv files (or of placement folders holding them)")
    here = _mukca_placement(path)
    placements = [(path.name, here)] if here else [
        (sub.name, found) for sub in sorted(p for p in path.iterdir() if p.is_dir())
        if (found := _mukca_placement(sub))]
    if not placements:
        raise DatasetError(f"{path}: no hole_<k>.csv here nor in its sub-folders")
    q, point, setup = [], [], []
    for name, holes in placements:
        if "," in name or name != name.strip():
            raise DatasetError(f"{path}: placement folder {name!r} is no setup id (no commas or surrounding blanks)")
        for hole, rows in holes:
            q.append(rows)
            point += [hole] * len(rows)
            setup += [name] * len(rows)
    return {"q_rad": np.concatenate(q), "xyz_mm": None, "point": np.array(point, dtype=object),
            "setup": np.array(setup, dtype=object)}
