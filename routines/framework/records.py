"""A routine's dataset on disk: the seam between measuring and solving.

Every routine writes what it recorded before it solves, so any result can be re-solved
offline (``cellcal run ROUTINE --from DATASET``) and any routine tested by replaying one.
The file is CSV with a small header of metadata lines::

    # cellcal dataset
    # routine: tcp-laser
    # cell: sim (config/cells/sim.yaml)
    # robot: ur10e
    # cellcal: 0.1.0
    # created: 2026-11-22T15:30:00+00:00
    # complete: true
    # meta: {"speed_m_s": 0.04, ...}          (the routine's own scalars, one JSON object)
    sweep,edge,channel,t_s,x_m,...            (the routine's columns)
    0,blocked,0,1.2345,...

Columns are numbers, except those the routine names as text. The file is written to a
temporary name and renamed into place, so a reader never sees half a dataset; a routine
stopped by a fault writes what it has with ``complete: false``.

Reading checks the numbers as the measurement CSV's are checked: each is finite (``nan``
only in the columns a routine names as sometimes not applicable, ``nan_columns``) and
within what its unit allows, read from the end of the column's name (``_mm``, ``_m``: 100 m;
``_rad``, ``_deg``: two turns; anything else: 1e10, beyond any count or time in seconds of a
run). A row that repeats an earlier one exactly is a copy, not a measurement: the dataset
keeps them in ``repeated_rows``, and the solve says its standard deviations are too small.
"""
from __future__ import annotations

import csv
import io
import json
import math
import os
from dataclasses import dataclass, field
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path

import numpy as np

from cellcal.routines.framework.base import jsonable
from cellcal.measurements.table import MAX_JOINT, MAX_POSITION_MM, DatasetError

MAGIC = "# cellcal dataset"
HEADER_KEYS = ("routine", "cell", "robot", "cellcal", "created", "complete", "meta")
# |value| allowed by the unit a column's name ends in: (suffix, bound, what a larger value would be)
UNIT_BOUNDS = (("_mm", MAX_POSITION_MM, "not a position in a cell (over 100 m away)"),
               ("_m", MAX_POSITION_MM / 1e3, "not a position in a cell (over 100 m away)"),
               ("_rad", MAX_JOINT["rad"], "beyond two turns"),
               ("_deg", MAX_JOINT["deg"], "beyond two turns"))
OTHER_BOUND = 1e10  # counts, indices, directions, times in s, speeds: nothing of a run is this large


def cellcal_version() -> str:
    try:
        return metadata.version("cellcal")
    except metadata.PackageNotFoundError:
        return "unknown"


@dataclass
class Dataset:
    routine: str
    columns: dict[str, np.ndarray]  # name -> (N,) numbers, or text (dtype str) for text columns
    meta: dict = field(default_factory=dict)  # JSON-able scalars and lists
    cell: str = ""
    robot: str = ""
    complete: bool = True
    created: str = ""
    version: str = ""
    path: str | None = None
    repeated_rows: list[tuple[int, int]] = field(default_factory=list)  # (line, line it repeats), when read

    @classmethod
    def of_rows(cls, routine: str, rows: list[dict], meta: dict, text_columns=()) -> "Dataset":
        """A dataset of rows, each a dict of column -> value (the first row names the columns):
        numbers, text in `text_columns`."""
        return cls(routine, {k: np.array([row[k] for row in rows], dtype=str if k in text_columns else float)
                             for k in rows[0]}, meta)

    def __len__(self) -> int:
        return len(next(iter(self.columns.values()))) if self.columns else 0

    def __getitem__(self, name: str) -> np.ndarray:
        return self.columns[name]

    def stack(self, *names: str) -> np.ndarray:
        return np.column_stack([self.columns[n] for n in names])

    def write(self, path: str | Path) -> Path:
        """Write atomically (temporary file, then rename); returns the path."""
        path = Path(path)
        lengths = {len(v) for v in self.columns.values()}
        if len(lengths) > 1:
            raise ValueError(f"columns of different lengths: {sorted(lengths)}")
        self.created = self.created or datetime.now(timezone.utc).isoformat(timespec="seconds")
        self.version = self.version or cellcal_version()
        out = io.StringIO()
        out.write(f"{MAGIC}\n# routine: {self.routine}\n# cell: {self.cell}\n# robot: {self.robot}\n"
                  f"# cellcal: {self.version}\n# created: {self.created}\n"
                  f"# complete: {'true' if self.complete else 'false'}\n"
                  f"# meta: {json.dumps(self.meta, sort_keys=True, default=jsonable)}\n")
        writer = csv.writer(out, lineterminator="\n")
        names = list(self.columns)
        writer.writerow(names)
        for row in zip(*(self.columns[n] for n in names)):
            writer.writerow([_cell_text(v) for v in row])
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        try:
            with open(tmp, "w", encoding="utf-8", newline="") as f:
                f.write(out.getvalue())
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, path)
        finally:
            if tmp.exists():
                tmp.unlink()
        self.path = str(path)
        return path


def _cell_text(value) -> str:
    if isinstance(value, (str, np.str_)):
        return str(value)
    value = float(value)
    return repr(value) if math.isfinite(value) else "nan"


def read_dataset(path: str | Path, routine: str | None = None, text_columns=(), nan_columns=()) -> Dataset:
    """Read a routine's dataset; `routine` (if given) must match the file's. `nan_columns`: numeric
    columns where ``nan`` means "not applicable" (elsewhere it is refused). Raises DatasetError naming
    the file, line and column."""
    name = os.fspath(path)
    try:
        lines = Path(name).read_text(encoding="utf-8").splitlines()
    except FileNotFoundError:
        raise DatasetError(f"{name}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{name}: cannot read: {exc}") from None
    if not lines or lines[0].strip() != MAGIC:
        raise DatasetError(f"{name}:1: not a cellcal routine dataset (first line must be '{MAGIC}')")
    header, i = {}, 1
    while i < len(lines) and lines[i].startswith("#"):
        key, sep, value = lines[i][1:].partition(":")
        if sep and key.strip() in HEADER_KEYS:
            header[key.strip()] = value.strip()
        i += 1
    for key in ("routine", "complete", "meta"):
        if key not in header:
            raise DatasetError(f"{name}: header line '# {key}: ...' is missing")
    if routine is not None and header["routine"] != routine:
        raise DatasetError(f"{name}: a dataset of routine {header['routine']!r}, not of {routine!r}")
    try:
        meta = json.loads(header["meta"], parse_constant=_no_constant)
    except json.JSONDecodeError as exc:
        raise DatasetError(f"{name}: header 'meta' is not one JSON object: {exc}") from None
    except ValueError as exc:
        raise DatasetError(f"{name}: header 'meta': {exc}") from None
    if not isinstance(meta, dict):
        raise DatasetError(f"{name}: header 'meta' is not one JSON object")
    rows = list(csv.reader(lines[i:]))
    if not rows:
        raise DatasetError(f"{name}:{i + 1}: no column header")
    names = [n.strip() for n in rows[0]]
    if len(set(names)) != len(names) or not all(names):
        raise DatasetError(f"{name}:{i + 1}: empty or repeated column names")
    bounds = {n: _bound(n) for n in names}
    values: dict[str, list] = {n: [] for n in names}
    seen: dict[tuple, int] = {}
    repeated: list[tuple[int, int]] = []
    for k, row in enumerate(rows[1:], start=i + 2):
        if not row:
            continue
        if len(row) != len(names):
            raise DatasetError(f"{name}:{k}: row has {len(row)} fields, header has {len(names)}")
        for n, text in zip(names, row):
            if n in text_columns:
                values[n].append(text)
                continue
            try:
                v = float(text)
            except ValueError:
                raise DatasetError(f"{name}:{k}: column {n!r}: {text[:24]!r} is not a number") from None
            if not math.isfinite(v) and not (math.isnan(v) and n in nan_columns):
                raise DatasetError(f"{name}:{k}: column {n!r}: {text.strip()[:24]!r} is not finite (a value "
                                   "was lost or edited: no measurement is nan or infinite)")
            limit, why = bounds[n]
            if abs(v) > limit:
                raise DatasetError(f"{name}:{k}: column {n!r}: {text.strip()[:24]} is {why} "
                                   f"(|value| must be at most {limit:g})")
            values[n].append(v)
        key = tuple(row)
        if key in seen:
            repeated.append((k, seen[key]))
        else:
            seen[key] = k
    columns = {n: np.array(v, dtype=str if n in text_columns else float) for n, v in values.items()}
    return Dataset(header["routine"], columns, meta, header.get("cell", ""), header.get("robot", ""),
                   header["complete"] == "true", header.get("created", ""), header.get("cellcal", ""), name,
                   repeated)


def _bound(column: str) -> tuple[float, str]:
    """The largest |value| a column may hold, by the unit its name ends in, and what a larger one is."""
    for suffix, limit, why in UNIT_BOUNDS:
        if column.endswith(suffix):
            return limit, why
    return OTHER_BOUND, "beyond any number a run records"


def _no_constant(text: str):
    raise ValueError(f"{text} is not a number a dataset's meta may hold")


def repeated_rows_note(dataset: Dataset) -> str | None:
    """What a dataset's repeated rows mean for its result, or None when it has none."""
    if not dataset.repeated_rows:
        return None
    line, first = dataset.repeated_rows[0]
    return (f"{len(dataset.repeated_rows)} of {len(dataset)} rows of {dataset.path} repeat an earlier row exactly "
            f"(line {line} is line {first} again): copies, not measurements; the fit counts them as independent "
            "measurements, so the standard deviations (+-) are too small")
