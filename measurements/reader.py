"""Reading the measurement CSV (the format: :mod:`.table`): one check after another, the
first problem refused with its file, line and column; nothing is partly loaded."""
from __future__ import annotations

import csv
import os
import re
import stat

import numpy as np

from cellcal.measurements.table import (DEFAULT_SETUP, DEFAULT_TARGET, JOINT_COLUMN, MAX_JOINT, MAX_PAYLOAD_KG,
                                        MAX_POSITION_MM, QUAT, SCALARS, SPLITS, XYZ, DatasetError,
                                        MeasurementTable)

# Stricter than float(): no "1_000", no non-ASCII digits, no nan/inf.
_NUMBER = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?")


def read_measurements(path, n_joints: int) -> MeasurementTable:
    """Read and validate a measurement file for a robot model with ``n_joints`` joints.

    Lean on large files: the text is split into lines once, and the values are parsed a
    block of rows at a time into one float array per column (no Python object per cell).
    Every problem is still reported as the first one in the order of the checks (a column's
    values are checked in column order, each column over all rows), naming line and column.
    """
    if int(n_joints) < 1:
        raise ValueError(f"n_joints must be >= 1, got {n_joints}")
    name = os.fspath(path)
    lines, records, quoted = _records(name)
    if not len(records):
        raise DatasetError(f"{name}: empty file: no header line (only comments or blank lines)")
    header = [h.strip() for h in _fields(lines, records[0], quoted)]
    where = f"{name}:{records[0] + 1}"
    cols, joints, unit = _check_header(where, header, int(n_joints))
    rows = records[1:]
    if not len(rows):
        raise DatasetError(f"{where}: header but no measurement rows")
    for i in rows:
        count = len(quoted[i]) if i in quoted else lines[i].count(",") + 1
        if count != len(header):
            raise DatasetError(f"{name}:{i + 1}: row has {count} fields, header has {len(header)}")
    lines_1 = rows + 1  # physical line of each row, 1-based

    point_form = "point" in cols
    # in the point form a position cell may be empty (a point row): those columns are parsed below, row by row
    numeric = [*joints, *(() if point_form else XYZ), *(c for c in SCALARS if c in cols),
               *(QUAT if "qw" in cols else ())]
    text_cols = [c for c in cols if c not in numeric and c not in joints]
    values = {c: np.empty(len(rows)) for c in numeric}
    texts: dict[str, list[str]] = {c: [] for c in text_cols}
    first_bad: dict[str, tuple[int, str]] = {}  # column -> (row, message) of its first unreadable value
    for start in range(0, len(rows), _BLOCK_ROWS):
        block = rows[start: start + _BLOCK_ROWS]
        split = [_fields(lines, i, quoted) for i in block]
        for c in numeric:
            if c in first_bad:
                continue
            cells = [f[cols[c]] for f in split]
            parsed, bad = _parse_block(cells)
            if bad is not None:
                text = cells[bad]
                first_bad[c] = (start + bad, f"{name}:{block[bad] + 1}: column {c!r}: {text!r} is "
                                             f"{_what_is_wrong(text)}")
            else:
                values[c][start: start + len(block)] = parsed
        for c in text_cols:
            texts[c].extend(f[cols[c]] for f in split)

    def column(c, limit=None, unit_=None, why=None):
        if c in first_bad:
            raise DatasetError(first_bad[c][1])
        if limit is not None:
            over = np.flatnonzero(np.abs(values[c]) > limit)
            if over.size:
                text = _fields(lines, rows[over[0]], quoted)[cols[c]].strip()
                raise DatasetError(f"{name}:{lines_1[over[0]]}: column {c!r}: {text} {unit_} is {why} "
                                   f"(|value| must be at most {limit:g})")
        return values[c]

    turns = "beyond two turns, further than any joint turns" + (" (degrees under a _rad header?)" if unit == "rad"
                                                                else "")
    q = np.column_stack([column(c, MAX_JOINT[unit], unit, turns) for c in joints])
    if point_form:
        point, setup, xyz = _point_columns(name, lines_1, texts, cols, len(rows))
    else:
        point = setup = None
        xyz = np.column_stack([column(c, MAX_POSITION_MM, "mm",
                                      "not a position a measuring instrument gives (over 100 m away)") for c in XYZ])
    scalars = {c: column(c) if c in cols else None for c in SCALARS}
    if scalars["payload_kg"] is not None:
        column("payload_kg", MAX_PAYLOAD_KG, "kg", "more than any arm carries")

    quat = None
    if "qw" in cols:
        quat = np.column_stack([column(c) for c in QUAT])
        norm = np.linalg.norm(quat, axis=1)
        bad = np.flatnonzero(norm < 1e-9)
        if bad.size:
            raise DatasetError(f"{name}:{lines_1[bad[0]]}: columns 'qw','qx','qy','qz': quaternion has zero norm")
        quat = quat / norm[:, None]

    target_names, target = (DEFAULT_TARGET,), np.zeros(len(rows), dtype=int)
    if "target" in cols:
        ids = [v.strip() for v in texts.pop("target")]
        empty = next((k for k, v in enumerate(ids) if not v), None)
        if empty is not None:
            raise DatasetError(f"{name}:{lines_1[empty]}: column 'target': empty target id")
        target_names = tuple(dict.fromkeys(ids))
        index = {t: i for i, t in enumerate(target_names)}
        target = np.fromiter((index[v] for v in ids), dtype=int, count=len(ids))

    split_col = None
    if "split" in cols:
        given = [v.strip() for v in texts.pop("split")]
        wrong = next((k for k, v in enumerate(given) if v not in SPLITS), None)
        if wrong is not None:
            raise DatasetError(f"{name}:{lines_1[wrong]}: column 'split': {given[wrong]!r} is not 'cal' or 'val'")
        split_col = np.array(given, dtype=str)

    extra = {c: tuple(texts[c]) for c in text_cols if c in texts}
    return MeasurementTable(
        path=name, q_rad=np.deg2rad(q) if unit == "deg" else q, xyz_mm=xyz, target=target,
        target_names=target_names, line=lines_1.astype(int), quat=quat, split=split_col, extra=extra,
        joint_unit=unit, point=point, setup=setup, **scalars,
    )


def _point_columns(name, lines_1, texts, cols, n):
    """point, setup and positions of a file with a point column; each row has a point or a position."""
    ids = [v.strip() for v in texts.pop("point")]
    point = np.array(ids, dtype=str)
    is_point = point != ""
    xyz = np.full((n, 3), np.nan)
    have = [c for c in XYZ if c in cols]
    cells = {c: [v.strip() for v in texts.pop(c)] for c in have}
    for c in have:  # a point row leaves the position empty; a position row fills all three
        filled = np.array([v != "" for v in cells[c]], dtype=bool)
        both = np.flatnonzero(filled & is_point)
        if both.size:
            k = both[0]
            raise DatasetError(f"{name}:{lines_1[k]}: columns 'point' and {c!r}: a point ({ids[k]!r}) and a position "
                               f"({cells[c][k]}) in one row; a row is either a measured position (x_mm, y_mm, z_mm) "
                               "or the fixed point the target sat at (point), never both")
    for k in np.flatnonzero(~is_point):
        missing = [c for c in XYZ if c not in cols or cells[c][k] == ""]
        if missing:
            what = ("neither a point nor a position" if len(missing) == 3 else
                    f"a position without {', '.join(missing)}")
            raise DatasetError(f"{name}:{lines_1[k]}: column {missing[0]!r}: {what}; give the point the target sat at "
                               "(point) or all of x_mm, y_mm, z_mm")
    measured = np.flatnonzero(~is_point)
    for j, c in enumerate(XYZ):
        if not measured.size:
            break
        parsed, bad = _parse_block([cells[c][k] for k in measured])
        if bad is not None:
            text = cells[c][measured[bad]]
            raise DatasetError(f"{name}:{lines_1[measured[bad]]}: column {c!r}: {text!r} is {_what_is_wrong(text)}")
        over = np.flatnonzero(np.abs(parsed) > MAX_POSITION_MM)
        if over.size:
            k = measured[over[0]]
            raise DatasetError(f"{name}:{lines_1[k]}: column {c!r}: {cells[c][k]} mm is not a position a measuring "
                               f"instrument gives (over 100 m away) (|value| must be at most {MAX_POSITION_MM:g})")
        xyz[measured, j] = parsed
    if "setup" in cols:
        given = [v.strip() for v in texts.pop("setup")]
        stray = next((k for k in measured if given[k]), None)
        if stray is not None:
            raise DatasetError(f"{name}:{lines_1[stray]}: column 'setup': {given[stray]!r} on a row with a measured "
                               "position; a setup is a placement of the fixture and belongs to point rows only")
        setup = np.array([(g or DEFAULT_SETUP) if p else "" for g, p in zip(given, is_point)], dtype=str)
    else:
        setup = np.where(is_point, DEFAULT_SETUP, "").astype(str)
    return point, setup, xyz


_BLOCK_ROWS = 8192
# Characters of the numbers the format takes (with separators and surrounding blanks): a block
# made only of these parses with float() exactly as _NUMBER would judge it, cell by cell.
_ONLY_NUMBER_CHARS = re.compile(r"[^0-9eE+\-.,\s]")


def _parse_block(cells: list[str]):
    """Floats of one column's cells in a block, and the index of the first unreadable one (or None)."""
    joined = ",".join(cells)
    if not _ONLY_NUMBER_CHARS.search(joined) and joined.count(",") == len(cells) - 1:
        try:
            out = np.fromiter(map(float, cells), dtype=float, count=len(cells))
        except ValueError:
            out = None
        if out is not None:
            finite = np.isfinite(out)
            return out, None if finite.all() else int(np.flatnonzero(~finite)[0])
    for k, text in enumerate(cells):  # the slow way: find the first bad cell
        s = text.strip()
        if not _NUMBER.fullmatch(s) or not np.isfinite(float(s)):
            return None, k
    return np.fromiter(map(float, cells), dtype=float, count=len(cells)), None


def _what_is_wrong(text: str) -> str:
    try:
        return "not finite" if not np.isfinite(float(text.strip())) else "not a number"
    except ValueError:
        return "not a number"


def _fields(lines, i, quoted) -> list[str]:
    return quoted[i] if i in quoted else lines[i].split(",")


def _records(name: str):
    """The file's lines (line ending stripped), the 0-based indices of its non-comment,
    non-blank lines, and the fields of those lines that need a CSV parser (quotes)."""
    try:
        with open(name, "rb") as f:
            if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
                raise DatasetError(f"{name}: not a regular file (a device, a pipe or a folder cannot be a "
                                   "measurement file)")
            raw = f.read()
    except OSError as exc:
        raise DatasetError(f"{name}: cannot read file: {exc.strerror or exc}") from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        lineno = raw[: exc.start].count(b"\n") + 1
        raise DatasetError(f"{name}:{lineno}: not UTF-8 text (byte 0x{raw[exc.start]:02x})") from None
    del raw
    if "\r" in text and "\n" not in text:
        raise DatasetError(f"{name}: lines end in CR alone (old Mac line endings); save it with LF or "
                           "CRLF line endings")
    lines = text.split("\n")
    del text
    records = []
    quoted: dict[int, list[str]] = {}
    for i, line in enumerate(lines):
        if line.endswith("\r"):
            line = lines[i] = line.rstrip("\r")
        if not line.strip() or line.startswith("#"):
            continue
        records.append(i)
        if '"' in line or "\r" in line or "\0" in line:
            try:
                quoted[i] = next(csv.reader([line], strict=True))
            except csv.Error as exc:
                raise DatasetError(f"{name}:{i + 1}: malformed CSV: {exc}") from None
    return lines, np.array(records, dtype=int), quoted


def _check_header(where: str, header: list[str], n_joints: int):
    """Column positions, the joint column names q1..qN in order, and the joint unit."""
    cols: dict[str, int] = {}
    for i, h in enumerate(header):
        if not h:
            raise DatasetError(f"{where}: column {i + 1} of the header has no name")
        if h in cols:
            raise DatasetError(f"{where}: column {h!r}: duplicate header name (columns {cols[h] + 1} and {i + 1})")
        cols[h] = i

    found = [(int(m[1]), m[2], h) for h in header if (m := JOINT_COLUMN.fullmatch(h))]
    unit = found[0][1] if found else "rad"
    for _, u, h in found:
        if u != unit:
            raise DatasetError(f"{where}: column {h!r}: mixed joint units: {found[0][2]!r} is in {unit}, "
                               f"{h!r} in {u}; a file uses one unit for all joints")
    joint_range = f"q1_{unit}" + (f" .. q{n_joints}_{unit}" if n_joints > 1 else "")
    required = f"{joint_range} (or all _{'rad' if unit == 'deg' else 'deg'}), " + ", ".join(XYZ)
    for k, u, h in found:
        if k < 1 or h != f"q{k}_{u}":
            raise DatasetError(f"{where}: column {h!r}: joint columns are numbered q1, q2, .. without leading zeros")
    in_file = max((k for k, _, _ in found), default=0)
    if in_file > n_joints:
        h = next(h for k, _, h in found if k > n_joints)
        raise DatasetError(f"{where}: column {h!r}: the file has joint columns up to q{in_file}, "
                           f"the robot model has {n_joints} joints")
    joints = tuple(f"q{k}_{unit}" for k in range(1, n_joints + 1))
    if "setup" in cols and "point" not in cols:
        raise DatasetError(f"{where}: column 'setup': a setup without a 'point' column; setups group the rows of the "
                           "point form (point: the fixed point the target sat at)")
    positions = XYZ
    if "point" in cols:  # the point form: positions optional, but all three or none
        present_xyz = [c for c in XYZ if c in cols]
        positions = XYZ if present_xyz else ()
    for c in joints + positions:
        if c not in cols:
            plural = "" if len(found) == 1 else "s"
            counts = f" (the file has {len(found)} joint column{plural}, the robot model {n_joints} joints)" \
                if c in joints else ""
            raise DatasetError(f"{where}: missing required column {c!r}{counts}; "
                               f"a {n_joints}-joint robot needs {required}")
    present = [c for c in QUAT if c in cols]
    if 0 < len(present) < 4:
        missing = next(c for c in QUAT if c not in cols)
        raise DatasetError(f"{where}: column {missing!r} missing: partial quaternion "
                           f"(has {', '.join(present)}); give all of qw, qx, qy, qz or none")
    return cols, joints, unit


def joint_velocities(table: MeasurementTable) -> np.ndarray | None:
    """Joint velocities at each sample from optional ``dq1_rad_s`` ... ``dqN_rad_s`` (or
    ``_deg_s``) columns, as trigger data carries them; None when the file has none.

    All joints or none, one unit; bad values are refused like every other column.
    """
    n = table.q_rad.shape[1]
    for unit, factor in (("rad_s", 1.0), ("deg_s", np.pi / 180.0)):
        names = [f"dq{j}_{unit}" for j in range(1, n + 1)]
        present = [c for c in names if c in table.extra]
        if not present:
            continue
        if len(present) != n:
            missing = next(c for c in names if c not in table.extra)
            raise DatasetError(f"{table.path}: column {missing!r} missing: joint velocities need "
                               f"all of {names[0]} .. {names[-1]}")
        out = np.empty((len(table), n))
        for k, c in enumerate(names):
            texts = table.extra[c]
            for start in range(0, len(texts), _BLOCK_ROWS):
                cells = list(texts[start: start + _BLOCK_ROWS])
                parsed, bad = _parse_block(cells)
                if bad is not None:
                    raise DatasetError(f"{table.path}:{table.line[start + bad]}: column {c!r}: {cells[bad]!r} is "
                                       f"{_what_is_wrong(cells[bad])}")
                out[start: start + len(cells), k] = parsed
        return out * factor
    return None
