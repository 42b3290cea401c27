"""``cellcal compensate``: corrected joint values and Cartesian targets from a calibrated model.

TARGETS.csv: ``x_mm, y_mm, z_mm`` of the tool point in the robot base frame, optionally
``qw, qx, qy, qz`` (its orientation), ``q1_deg .. qN_deg`` (or ``_rad``: the program's
joints, i.e. the branch each target is reached in), ``payload_kg``; other columns are
copied through. OUT.csv: the input columns, the corrected joints, the corrected
Cartesian target (nominal forward kinematics of the corrected joints), the correction
and a status per row (``solvers.compensate``).
"""
from __future__ import annotations

import csv
import json
import time

import numpy as np
from scipy.spatial.transform import Rotation

from cellcal.config.model_files import load_calibrated, source_model
from cellcal.config.robot_files import load_robot
from cellcal.measurements.table import MAX_JOINT, MAX_POSITION_MM, MAX_PAYLOAD_KG
from cellcal.solvers.compensate import OK, compensate
from cellcal.solvers.effects import Context, approach_directions
from cellcal.cli.common import UsageError, counted, number, print_progress, writable_file

XYZ, QUAT = ("x_mm", "y_mm", "z_mm"), ("qw", "qx", "qy", "qz")
SHOWN_ROWS = 10  # rows named one by one in the text report
MAX_TOOL_MM = 5000.0  # a tool point 5 m from the flange is beyond any tool an arm carries


def add_parser(sub):
    p = sub.add_parser(
        "compensate", help="correct targets with a calibrated model: joints and Cartesian targets",
        description="For desired tool positions (and orientations) in the robot base frame, compute the joints "
                    "at which the calibrated model (geometry and effects) reaches them, starting from the nominal "
                    "inverse of the same branch; write them and the corrected Cartesian targets (nominal forward "
                    "kinematics of the corrected joints). Rows out of reach, outside the joint limits or near a "
                    "singularity are reported by row, never clipped.")
    p.add_argument("--robot", required=True, metavar="CALIBRATED.yaml",
                   help="calibrated robot model file (cellcal identify/analyze --write-model)")
    p.add_argument("--targets", required=True, metavar="TARGETS.csv",
                   help="x_mm, y_mm, z_mm [, qw, qx, qy, qz] [, q1_deg .. qN_deg (branch)] [, payload_kg]")
    p.add_argument("-o", "--out", required=True, metavar="OUT.csv", help="corrected targets to write")
    p.add_argument("--nominal", metavar="ROBOT",
                   help="the controller's nominal model (default: the model the calibration started from)")
    p.add_argument("--target", metavar="ID", help="which calibrated target offset is the tool point (default: the first)")
    p.add_argument("--tcp-mm", nargs=3, type=number(-MAX_TOOL_MM, MAX_TOOL_MM, unit="mm"), metavar=("X", "Y", "Z"),
                   help="tool point in the flange frame instead of a calibrated target offset (mm, each within "
                        f"+-{MAX_TOOL_MM:g})")
    p.add_argument("--seed-deg", nargs="+", type=number(-MAX_JOINT["deg"], MAX_JOINT["deg"], unit="deg"),
                   metavar="Q", help="joints (deg, each within two turns) of the branch to start from when TARGETS "
                                     "has no joint columns")
    p.add_argument("--unit", choices=("deg", "rad"), help="unit of the joint columns written (default: as TARGETS, "
                                                          "else deg)")
    p.add_argument("--max-correction-deg", type=number(0.0, 180.0, above=True, unit="deg"), default=1.0,
                   help="a row whose correction exceeds this is reported as near a singularity (above 0, at "
                        "most 180; default 1)")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(func=run)


def read_targets(path, n_joints: int) -> dict:
    """The target file's columns: header, text rows, xyz (N, 3), quat (N, 4) or None, q (N, nj) rad or None,
    joint unit, payload or None. One UsageError naming file, line and column for anything unusable."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            lines = [(i, row) for i, row in enumerate(csv.reader(f), start=1)
                     if row and not row[0].startswith("#") and any(c.strip() for c in row)]
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise UsageError(f"{path}: cannot read the targets: {getattr(exc, 'strerror', None) or exc}") from None
    if len(lines) < 2:
        raise UsageError(f"{path}: needs a header line and at least one target row")
    (header_line, header), rows = lines[0], lines[1:]
    header = [h.strip() for h in header]
    col = {h: i for i, h in enumerate(header)}
    if len(col) != len(header):
        raise UsageError(f"{path}:{header_line}: duplicate column names")
    for i, row in rows:
        if len(row) != len(header):
            raise UsageError(f"{path}:{i}: row has {len(row)} fields, header has {len(header)}")

    def numbers(name, limit, unit, why):
        """The column's values: finite, |value| at most `limit` (as the measurement CSV's columns)."""
        out = np.empty(len(rows))
        for k, (i, row) in enumerate(rows):
            try:
                out[k] = float(row[col[name]])
            except ValueError:
                out[k] = np.nan
            if not np.isfinite(out[k]):
                raise UsageError(f"{path}:{i}: column {name!r}: {row[col[name]]!r} is not a finite number")
            if abs(out[k]) > limit:
                raise UsageError(f"{path}:{i}: column {name!r}: {row[col[name]].strip()}{unit} is {why} "
                                 f"(|value| must be at most {limit:g})")
        return out

    missing = [c for c in XYZ if c not in col]
    if missing:
        raise UsageError(f"{path}:{header_line}: missing required column {missing[0]!r} (needs x_mm, y_mm, z_mm)")
    xyz = np.column_stack([numbers(c, MAX_POSITION_MM, " mm", "not a target any arm reaches (over 100 m away)")
                           for c in XYZ])
    quat = None
    if any(c in col for c in QUAT):
        if not all(c in col for c in QUAT):
            raise UsageError(f"{path}:{header_line}: give all of qw, qx, qy, qz or none")
        quat = np.column_stack([numbers(c, 1e6, "", "not a quaternion component (any scale up to 1e6 is taken)")
                                for c in QUAT])
        bad = np.flatnonzero(np.linalg.norm(quat, axis=1) < 1e-9)
        if bad.size:
            raise UsageError(f"{path}:{rows[bad[0]][0]}: columns qw..qz: quaternion has zero norm")
    q, unit = None, None
    for u in ("deg", "rad"):
        names = [f"q{j}_{u}" for j in range(1, n_joints + 1)]
        present = [n for n in names if n in col]
        if present and len(present) < n_joints:
            raise UsageError(f"{path}:{header_line}: joint columns {names[0]} .. {names[-1]}: all {n_joints} or none")
        if present:
            if q is not None:
                raise UsageError(f"{path}:{header_line}: joint columns in both deg and rad; use one unit")
            q = np.column_stack([numbers(n, MAX_JOINT[u], f" {u}", "beyond two turns of any joint")
                                 for n in names])
            q, unit = (np.deg2rad(q) if u == "deg" else q), u
    payload = numbers("payload_kg", MAX_PAYLOAD_KG, " kg", "more than any arm carries") if "payload_kg" in col else None
    return {"header": header, "rows": [r for _, r in rows], "lines": [i for i, _ in rows], "xyz": xyz, "quat": quat,
            "q": q, "unit": unit, "payload": payload}


def run(args) -> int:
    writable_file(args.out, "-o")
    calibrated = load_calibrated(args.robot)
    model = calibrated.model
    if len(model.chains) != 1:
        raise UsageError(f"{args.robot}: a tree model; compensate works on serial arms")
    nominal = load_robot(args.nominal or source_model(args.robot) or args.robot)
    if nominal.n_joints != model.n_joints:
        raise UsageError(f"--nominal {args.nominal}: {nominal.n_joints} joints, the calibrated model {model.n_joints}")
    if args.tcp_mm is not None:
        offset = np.array(args.tcp_mm)
    else:
        name = args.target or calibrated.target_names[0]
        if name not in calibrated.target_names:
            raise UsageError(f"--target {name}: not a target of {args.robot} "
                             f"({', '.join(calibrated.target_names)})")
        offset = calibrated.offsets[calibrated.target_names.index(name)]
    t = read_targets(args.targets, model.n_joints)
    n = len(t["xyz"])
    if t["q"] is not None:
        seed = t["q"]
    elif args.seed_deg is not None:
        if len(args.seed_deg) != model.n_joints:
            raise UsageError(f"--seed-deg: give {model.n_joints} joint values, got {len(args.seed_deg)}")
        seed = np.tile(np.deg2rad(args.seed_deg), (n, 1))
    else:
        raise UsageError(f"{args.targets}: no joint columns: give the branch with q1_deg .. q{model.n_joints}_deg "
                         "columns or --seed-deg")
    rot = None if t["quat"] is None else Rotation.from_quat(t["quat"][:, [1, 2, 3, 0]]).as_matrix()
    direction = approach_directions(seed)
    payload = t["payload"]

    def ctx_at(q, rows):
        return Context(direction=direction[rows], payload_kg=None if payload is None else payload[rows])

    started = time.perf_counter()
    result = compensate(nominal, calibrated, t["xyz"], rot, seed, offset_mm=offset, ctx_at=ctx_at,
                        max_correction_rad=np.deg2rad(args.max_correction_deg))
    seconds = time.perf_counter() - started
    unit = args.unit or t["unit"] or "deg"
    _write(args.out, t, result, unit, rot is not None)
    bad = np.flatnonzero(result.status != OK)
    for i in bad[:SHOWN_ROWS]:
        print_progress(f"{args.targets}:{t['lines'][i]}: {result.status[i]}"
                       + (f" (correction {np.rad2deg(result.correction_rad[i]):.3g} deg)" if result.status[i] != "unreachable" else ""))
    if len(bad) > SHOWN_ROWS:
        print_progress(f"... {counted(len(bad) - SHOWN_ROWS, 'more row')} not ok (column status in {args.out})")
    ok = result.status == OK
    summary = {"rows": n, "ok": int(ok.sum()),
               "not_ok": [{"line": int(t["lines"][i]), "status": str(result.status[i])} for i in bad],
               "correction_deg": {"max": float(np.rad2deg(result.correction_rad[ok].max(initial=0.0))),
                                  "mean": float(np.rad2deg(result.correction_rad[ok].mean())) if ok.any() else 0.0},
               "nominal_model": nominal.name, "out": str(args.out), "seconds": seconds}
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"compensated {summary['ok']} of {counted(n, 'target')} with {args.robot} (nominal: {nominal.name}) in "
              f"{seconds:.2f} s; joint corrections mean {summary['correction_deg']['mean']:.4f} deg, max "
              f"{summary['correction_deg']['max']:.4f} deg; {counted(len(bad), 'row')} not ok; written to {args.out}")
    return 0


def _write(path, t, result, unit: str, with_rotation: bool) -> None:
    nj = result.q.shape[1]
    scale = np.rad2deg if unit == "deg" else (lambda v: v)
    added = ([f"q{j}_{unit}" for j in range(1, nj + 1)] + [f"q{j}_nominal_{unit}" for j in range(1, nj + 1)]
             + ["x_cmd_mm", "y_cmd_mm", "z_cmd_mm"] + (["qw_cmd", "qx_cmd", "qy_cmd", "qz_cmd"] if with_rotation else [])
             + ["correction_deg", "status"])
    quat = Rotation.from_matrix(result.rotation).as_quat()[:, [3, 0, 1, 2]]
    try:
        with open(path, "w", newline="", encoding="utf-8") as f:
            w = csv.writer(f, lineterminator="\n")
            w.writerow([h for h in t["header"] if h not in added] + added)
            keep = [k for k, h in enumerate(t["header"]) if h not in added]
            for i, row in enumerate(t["rows"]):
                values = []
                if result.status[i] == OK:
                    values = [*scale(result.q[i]), *scale(result.q_nominal[i]), *result.position_mm[i],
                              *(quat[i] if with_rotation else ())]
                    values = [f"{v:.10g}" for v in values]
                else:
                    values = [""] * (len(added) - 2)
                w.writerow([row[k] for k in keep] + values + [f"{np.rad2deg(result.correction_rad[i]):.6g}",
                                                              result.status[i]])
    except OSError as exc:
        raise UsageError(f"-o {path}: cannot write: {exc.strerror or exc}") from None
