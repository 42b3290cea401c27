"""``cellcal compensate``: corrected joint values and Cartesian targets from a calibrated model.

TARGETS.csv: ``x_mm, y_mm, z_mm`` of the tool point in the frame ``--frame`` names (the
controller's base frame by default; ``solvers.compensation.compensate.FRAMES``), optionally
``qw, qx, qy, qz`` (its orientation), ``q1_deg .. qN_deg`` (or ``_rad``: the program's
joints, i.e. the branch each target is reached in), ``payload_kg``; other columns are
copied through. OUT.csv: the input columns, the corrected joints, the corrected
Cartesian target (nominal forward kinematics of the corrected joints, controller frame),
the correction and a status per row (``solvers.compensation.compensate``).
"""
from __future__ import annotations

import csv
import json
import sys
import time

import numpy as np
from scipy.spatial.transform import Rotation

from cellcal.config.model_files import calibration_section, covariance, drawn_targets, load_calibrated
from cellcal.config.robot_files import ModelError, load_robot
from cellcal.measurements.table import MAX_JOINT, MAX_POSITION_MM, MAX_PAYLOAD_KG
from cellcal.solvers.compensation.compensate import (FRAMES, JOINT_LIMITS, NOMINAL_MISMATCH_MM, OK, SINGULAR,
                                                     SINGULAR_MM_PER_RAD, UNREACHABLE, compensate, controller_frame,
                                                     nominal_mismatch_mm, targets_in_model_frame)
from cellcal.solvers.compensation.tool_map import tool_map
from cellcal.solvers.analysis.effects import Context, approach_directions
from cellcal.cli.common import UsageError, counted, number, print_progress, writable_file

XYZ, QUAT = ("x_mm", "y_mm", "z_mm"), ("qw", "qx", "qy", "qz")
SHOWN_ROWS = 10  # rows named one by one in the text report
MAX_TOOL_MM = 5000.0  # a tool point 5 m from the flange is beyond any tool an arm carries


def add_parser(sub):
    p = sub.add_parser(
        "compensate", help="correct targets with a calibrated model: joints and Cartesian targets",
        description="For desired tool positions (and orientations) in the frame --frame names, compute the "
                    "joints at which the calibrated model (geometry and effects) reaches them, starting from the "
                    "nominal inverse of the same branch; write them and the corrected Cartesian targets (nominal "
                    "forward kinematics of the corrected joints, in the controller's base frame). Rows out of reach, "
                    "outside the joint limits or at a singular configuration (judged by the Jacobian) are reported "
                    "by row, never clipped.")
    p.add_argument("--robot", required=True, metavar="CALIBRATED.yaml",
                   help="calibrated robot model file (cellcal identify/analyze --write-model)")
    given = p.add_mutually_exclusive_group(required=True)  # what the targets come in: a table or a program
    given.add_argument("--targets", metavar="TARGETS.csv",
                       help="x_mm, y_mm, z_mm [, qw, qx, qy, qz] [, q1_deg .. qN_deg (branch)] [, payload_kg]")
    given.add_argument("--program", metavar="PROG.script",
                       help="a URScript program instead: every movej/movel/movep/movec target written as a literal "
                            "pose p[...] or joint list [...] is compensated as the controller reads it (a pose is the "
                            "TCP of the set_tcp in force, else --tcp-mm or the calibrated target, in the controller's "
                            "base frame, solved from the previous target's joints or --seed-deg); -o gets the same "
                            "program with only those numbers changed. Targets computed at run time are listed, not "
                            "guessed (docs/programs.md)")
    p.add_argument("-o", "--out", required=True, metavar="OUT",
                   help="corrected targets to write (OUT.csv; with --program the compensated program, not the "
                        "program itself)")
    p.add_argument("--allow-partial", action="store_true",
                   help="with --program: write the program even when some literal targets could not be compensated "
                        "(out of reach, outside the joint limits, at a singularity; left as written and listed); "
                        "without it such a program ends with status 1 and nothing is written")
    p.add_argument("--nominal", metavar="ROBOT",
                   help="the controller's nominal model (default: the model the calibration started from)")
    p.add_argument("--target", metavar="ID", help="which measured target is the tool point (default: the first): its "
                                                  "drawn offset where the model file records drawn targets, else its "
                                                  "calibrated offset")
    p.add_argument("--tcp-mm", nargs=3, type=number(-MAX_TOOL_MM, MAX_TOOL_MM, unit="mm"), metavar=("X", "Y", "Z"),
                   help="tool point in the flange frame as the controller knows it, instead of a measured target (mm, "
                        f"each within +-{MAX_TOOL_MM:g}); mapped into the calibrated model through the model file's "
                        "drawn targets (docs/programs.md, Tools)")
    p.add_argument("--seed-deg", nargs="+", type=number(-MAX_JOINT["deg"], MAX_JOINT["deg"], unit="deg"),
                   metavar="Q", help="joints (deg, each within two turns) of the branch to start from when TARGETS "
                                     "has no joint columns")
    p.add_argument("--unit", choices=("deg", "rad"), help="unit of the joint columns written (default: as TARGETS, "
                                                          "else deg)")
    p.add_argument("--frame", choices=FRAMES,
                   help="the frame TARGETS is in. base (default): the controller's base frame, as its nominal "
                        "kinematics realise it on this robot: poses from a robot program, the teach pendant or an "
                        "offline programming system (the frame in which the nominal kinematics are right on "
                        "average: a least-squares fit over the joint space). instrument: the measuring "
                        "instrument's frame, e.g. a workpiece measured by the tracker the calibration used "
                        "(mapped with the model file's calibration.base). model: the calibrated model's own base "
                        "frame, a convention of the calibration: only for targets computed with this model file")
    p.add_argument("--max-correction-deg", type=number(0.0, 180.0, above=True, unit="deg"), default=1.0,
                   help="warn of rows whose joints move by more than this (above 0, at most 180; default 1). Such "
                        "rows are compensated: a large correction is not a singularity (near one, a small "
                        "Cartesian correction needs large joint moves); singular configurations are judged by the "
                        "Jacobian and reported as near_singularity")
    p.add_argument("--force", action="store_true",
                   help="compensate a program or target file that cellcal compensated before (a program's last "
                        "comment line, a target file's compensated_with column say so): its targets move a second "
                        "time. Without it such a file is refused, status 2")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(func=run)


MARK = "cellcal compensated:"  # the comment line a compensated program carries
MARK_COLUMN = "compensated_with"  # the column a compensated target file carries (a CSV reader takes no comments)


def mark(args, nominal) -> str:
    """What this run's output is marked with (after MARK: a program's last comment line, a target file's
    MARK_COLUMN): the model (its file's content hash), the nominal model and the date, so that
    compensating the output again is caught."""
    import datetime
    import hashlib

    from cellcal.config.robot_files import resolve_robot
    path = resolve_robot(args.robot)
    digest = hashlib.sha256(path.read_bytes()).hexdigest()[:16]
    when = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    return (f"with {path.name} (sha256 {digest}), nominal {nominal.name}, {when}: compensating this again would "
            "move its targets a second time")


def marked(lines) -> str | None:
    """The first marker line among `lines` (text lines of a program or a target file), without its '#'."""
    for line in lines:
        text = line.strip()
        if text.startswith("#") and text.lstrip("#").strip().startswith(MARK):
            return text.lstrip("#").strip()
    return None


def refuse_marked(args, path, found: str | None) -> None:
    if found is not None and not args.force:
        raise UsageError(f"{path}: already compensated ({found.removeprefix(MARK).strip().split(':')[0]}): compensating "
                         "it again would move every target a second time; give the original, or --force")


def read_targets(path, n_joints: int) -> dict:
    """The target file's columns: header, text rows, xyz (N, 3), quat (N, 4) or None, q (N, nj) rad or None,
    joint unit, payload or None. One UsageError naming file, line and column for anything unusable."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            every = list(enumerate(csv.reader(f), start=1))
        lines = [(i, row) for i, row in every if row and not row[0].startswith("#") and any(c.strip() for c in row)]
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
    done = sorted({row[col[MARK_COLUMN]].strip() for _, row in rows} - {""}) if MARK_COLUMN in col else []
    return {"header": header, "rows": [r for _, r in rows], "lines": [i for i, _ in rows], "xyz": xyz, "quat": quat,
            "q": q, "unit": unit, "payload": payload, "compensated": f"{MARK} {done[0]}" if done else None}


def run(args) -> int:
    if args.allow_partial and args.program is None:
        raise UsageError("--allow-partial: only with --program (a CSV reports the rows it could not solve by row)")
    if args.program is not None and args.frame not in (None, "base"):
        raise UsageError(f"--frame {args.frame}: a URScript program's poses are in the controller's base frame; "
                         "--frame is for --targets")
    writable_file(args.out, "-o")
    calibrated = load_calibrated(args.robot)
    model = calibrated.model
    if len(model.chains) != 1:
        raise UsageError(f"{args.robot}: a tree model; compensate works on serial arms")
    record = calibration_section(args.robot)  # what the file says of its calibration, read once
    source = record.mapping.get("source_model")
    nominal = load_robot(args.nominal or source or args.robot)
    if nominal.n_joints != model.n_joints:
        raise UsageError(f"--nominal {args.nominal}: {nominal.n_joints} joints, the calibrated model {model.n_joints}")
    tools = _tool_map(record, calibrated, nominal if args.nominal is None or source is None else load_robot(source))
    if args.tcp_mm is not None:
        tcp = np.array(args.tcp_mm)
    else:
        name = args.target or calibrated.target_names[0]
        if name not in calibrated.target_names:
            raise UsageError(f"--target {name}: not a target of {args.robot} "
                             f"({', '.join(calibrated.target_names)})")
        which = calibrated.target_names.index(name)
        tcp = (calibrated.offsets if tools.drawn is None else tools.drawn)[which]
    offset = tools.to_model(tcp)  # the tool point in the calibrated end frame
    _same_arm(args, calibrated, nominal, offset, source)
    _fit_warning(args, record.mapping)
    if args.program is not None:  # a URScript program in, the same program compensated out
        return run_program(args, calibrated, nominal, tcp, tools)
    t = read_targets(args.targets, model.n_joints)
    refuse_marked(args, args.targets, t["compensated"])
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

    frame = args.frame or "base"
    started = time.perf_counter()
    at_model, at_controller = tools.frame_points(tcp)
    controller = controller_frame(calibrated, nominal, offset_mm=at_model, nominal_offset_mm=at_controller)
    xyz, rot_model = targets_in_model_frame(calibrated, nominal, t["xyz"], rot, frame, controller=controller)
    result = compensate(nominal, calibrated, xyz, rot_model, seed, offset_mm=offset, nominal_offset_mm=tcp,
                        ctx_at=ctx_at, controller=controller)
    bound = tools.bound_mm(result.q, tcp)
    seconds = time.perf_counter() - started
    unit = args.unit or t["unit"] or "deg"
    _write(args.out, t, result, unit, rot is not None, mark(args, nominal), bound)
    bad = np.flatnonzero(result.status != OK)
    reasons = {int(i): _reason(result, i, nominal) for i in bad}
    for i in bad[:SHOWN_ROWS]:
        print_progress(f"{args.targets}:{t['lines'][i]}: {result.status[i]}: {reasons[int(i)]}")
    if len(bad) > SHOWN_ROWS:
        print_progress(f"... {counted(len(bad) - SHOWN_ROWS, 'more row')} not ok (column status in {args.out})")
    ok = result.status == OK
    corrections = np.rad2deg(result.correction_rad[ok & np.isfinite(result.correction_rad)])
    large = np.flatnonzero(ok & (result.correction_rad > np.deg2rad(args.max_correction_deg)))
    for i in large[:SHOWN_ROWS]:
        print_progress(f"{args.targets}:{t['lines'][i]}: warning: compensated, but the joints move by "
                       f"{np.rad2deg(result.correction_rad[i]):.3g} deg (above --max-correction-deg "
                       f"{args.max_correction_deg:g}): near a singular configuration a small correction needs large "
                       "joint moves; check the motion into this target")
    if len(large) > SHOWN_ROWS:
        print_progress(f"... {counted(len(large) - SHOWN_ROWS, 'more row')} with a correction above "
                       f"{args.max_correction_deg:g} deg (column correction_deg in {args.out})")
    summary = {"rows": n, "ok": int(ok.sum()), "frame": frame,
               "not_ok": [{"line": int(t["lines"][i]), "status": str(result.status[i]), "reason": reasons[int(i)]}
                          for i in bad],
               "correction_deg": {"max": float(corrections.max(initial=0.0)),
                                  "mean": float(corrections.mean()) if corrections.size else 0.0},
               "large_correction": [{"line": int(t["lines"][i]),
                                     "correction_deg": float(np.rad2deg(result.correction_rad[i]))} for i in large],
               "max_correction_deg": args.max_correction_deg,
               "nominal_model": nominal.name, "out": str(args.out), "seconds": seconds,
               "compensated_before": t["compensated"], "tool": _tool_doc(tools, tcp, offset),
               "bound_mm": None if bound is None or not ok.any() else
               {"max": float(bound[ok].max()), "mean": float(bound[ok].mean())}}
    if t["compensated"] is not None:
        print_progress(f"{args.targets}: warning: compensated before ({t['compensated']}); --force compensated it "
                       "again: every target moved a second time")
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"compensated {summary['ok']} of {counted(n, 'target')} ({frame} frame) with {args.robot} (nominal: "
              f"{nominal.name}) in {seconds:.2f} s; joint corrections mean {summary['correction_deg']['mean']:.4f} "
              f"deg, max {summary['correction_deg']['max']:.4f} deg; {counted(len(bad), 'row')} not ok"
              + (f", {len(large)} above {args.max_correction_deg:g} deg (warned)" if len(large) else "")
              + f"; written to {args.out}")
        print(_tool_text(tools, tcp, offset, summary["bound_mm"]))
    return 0


def _tool_map(record, calibrated, source):
    """The model's ``ToolMap`` from its calibration section ``record``: its drawn targets, covariance and
    held-out error; ``source`` the nominal model it was calibrated from (which tells the held parameters
    from the estimated ones; --nominal when the file does not say)."""
    try:
        drawn = drawn_targets(record, calibrated.target_names)
        cov = covariance(record, calibrated.layout.names)
    except ModelError as exc:
        raise UsageError(str(exc)) from None
    heldout = (record.mapping.get("heldout") or {}).get("mean_mm")
    return tool_map(calibrated, source, drawn, heldout if isinstance(heldout, (int, float)) else None, cov)


def _tool_doc(tools, tcp, offset) -> dict:
    """The JSON's ``tool``: the default tool point as the controller knows it and in the calibrated end frame,
    the drawn targets it is mapped through and the spread the bounds take for what the calibration held."""
    return {"tcp_mm": [float(v) for v in tcp], "model_mm": [float(v) for v in offset],
            "drawn_targets": None if tools.drawn is None else tools.drawn.tolist(),
            "unseen_sd": {"deg": tools.sd_deg, "mm": tools.sd_mm}, "own_error_mm": tools.own_mm}


def _tool_text(tools, tcp, offset, bound) -> str:
    where = " ".join(f"{v:g}" for v in np.round(tcp, 4))
    model = " ".join(f"{v:g}" for v in np.round(offset, 4))
    if tools.drawn is None:
        text = (f"tool: ({where}) mm taken as a point of the calibrated end frame, as its target offsets are (the model "
                "file records no drawn targets, identify/analyze --drawn-target: a TCP given as drawn lands off by "
                "its difference from the calibrated offset)")
    else:
        text = f"tool: ({where}) mm as the controller knows it is ({model}) mm in the calibrated end frame"
    if bound is not None:
        text += (f"; where the targets land: within {bound['mean']:.3f} mm on average, {bound['max']:.3f} mm at most "
                 "(95 % bounds: the model's own error and the lever arm of what the calibration could not see)")
    return text


# a model whose own training rows it leaves this many times further off than their noise does not fit them
MISFIT_FACTOR = 5.0


def _fit_warning(args, record: dict) -> None:
    """Warn of a model that does not fit its own data (its calibration ``record``'s training rms far above
    the noise the data claim: written with --force over a failed fit, or from data with a wrong fixture)."""
    train = (record.get("train") or {})
    rms, noise = train.get("rms_mm"), train.get("noise_mm")
    if isinstance(rms, (int, float)) and isinstance(noise, (int, float)) and noise > 0 and rms > MISFIT_FACTOR * noise:
        print_progress(f"{args.robot}: warning: the model leaves its own training rows {rms:.3f} mm rms off, "
                       f"{rms / noise:.0f} times the {noise:.3f} mm their noise accounts for: it does not fit its "
                       "data (a wrong fixture distance?); its corrections may be wrong by as much")


def _same_arm(args, calibrated, nominal, offset, source: str | None) -> None:
    """Refuse a nominal model of another arm than the one calibrated (``source``: the one the file says
    it started from): its targets would move by the difference of two arms (hundreds of mm), not by a
    calibration's correction."""
    off_mm = nominal_mismatch_mm(calibrated, nominal, offset)
    if off_mm <= NOMINAL_MISMATCH_MM:
        return
    started = f"the calibration started from {source}" if source else "the model file does not say which model " \
                                                                      "the calibration started from"
    raise UsageError(f"--nominal {args.nominal or nominal.name}: its arm is up to {off_mm:.0f} mm from the calibrated "
                     f"one over the workspace (after the best base frame; a calibration changes a tool point by a few "
                     f"mm, at most {NOMINAL_MISMATCH_MM:g}): not the controller this model was calibrated for ({started})"
                     "; nothing written")


def _reason(result, i: int, nominal) -> str:
    """Why row i was not compensated, in words and numbers."""
    status = result.status[i]
    if status == UNREACHABLE:
        return (f"out of reach on this branch: the calibrated model's closest approach from the row's joints ends "
                f"{result.miss_mm[i]:.4g} mm from the target")
    if status == JOINT_LIMITS:
        q, limits = np.rad2deg(result.q[i]), np.rad2deg(nominal.joint_limits)
        j = int(np.argmax(np.maximum(limits[:, 0] - q, q - limits[:, 1])))
        return (f"the solution puts joint {j + 1} at {q[j]:.4g} deg, outside its limits {limits[j, 0]:g} .. "
                f"{limits[j, 1]:g} deg (not clipped)")
    if status == SINGULAR:
        return (f"at a singular configuration: the smallest singular value of the Jacobian there is "
                f"{result.sigma_min[i]:.3g} mm/rad (below {SINGULAR_MM_PER_RAD:g}: some joint motion of a radian "
                "barely moves the tool, so the joints are not determined)")
    return status


def _write(path, t, result, unit: str, with_rotation: bool, marker: str, bound=None) -> None:
    nj = result.q.shape[1]
    scale = np.rad2deg if unit == "deg" else (lambda v: v)
    added = ([f"q{j}_{unit}" for j in range(1, nj + 1)] + [f"q{j}_nominal_{unit}" for j in range(1, nj + 1)]
             + ["x_cmd_mm", "y_cmd_mm", "z_cmd_mm"] + (["qw_cmd", "qx_cmd", "qy_cmd", "qz_cmd"] if with_rotation else [])
             + ["correction_deg", "bound_mm", "status", MARK_COLUMN])
    quat = Rotation.from_matrix(result.rotation).as_quat()[:, [3, 0, 1, 2]]
    # the input's own joint columns (the branch each row was given in) are kept, renamed where the
    # solution's take their names: q1_deg -> q1_branch_deg; any other column the solution names is replaced
    branch = {f"q{j}_{unit}": f"q{j}_branch_{unit}" for j in range(1, nj + 1)}
    header = [branch.get(h, h) for h in t["header"]]
    keep = [k for k, h in enumerate(header) if h not in added]
    try:
        with open(path, "w", newline="", encoding="utf-8") as f:
            w = csv.writer(f, lineterminator="\n")
            w.writerow([header[k] for k in keep] + added)
            for i, row in enumerate(t["rows"]):
                values = []
                if result.status[i] == OK:  # q_nominal is NaN where the nominal model itself misses: left empty
                    values = [*scale(result.q[i]), *scale(result.q_nominal[i]), *result.position_mm[i],
                              *(quat[i] if with_rotation else ())]
                    values = [f"{v:.10g}" if np.isfinite(v) else "" for v in values]
                else:
                    values = [""] * (len(added) - 4)  # correction, bound, status and marker follow
                correction = np.rad2deg(result.correction_rad[i])
                within = "" if bound is None or result.status[i] != OK else f"{bound[i]:.4g}"
                w.writerow([row[k] for k in keep] + values + [f"{correction:.6g}" if np.isfinite(correction) else "",
                                                              within, result.status[i], marker])
    except OSError as exc:
        raise UsageError(f"-o {path}: cannot write: {exc.strerror or exc}") from None


def run_program(args, calibrated, nominal, tcp_mm, tools) -> int:
    """``--program``: the URScript program with its literal targets compensated (programs/apply.py) and a
    report per target. Status 1, nothing written, when a literal target could not be compensated, unless
    ``--allow-partial``; a program that cannot be read is a UsageError before anything is computed."""
    import os
    from collections import Counter

    from cellcal.programs.apply import OK as COMPENSATED, compensate_program
    from cellcal.programs.urscript import ProgramError, encode, read_program, rewrite

    if args.unit is not None:
        raise UsageError("--unit: the joint unit of a CSV's columns; a URScript program keeps its radians")
    if os.path.exists(args.out) and os.path.exists(args.program) and os.path.samefile(args.out, args.program):
        raise UsageError(f"-o {args.out}: is the program itself; write the compensated program to another file "
                         "(the original is what a later calibration compensates again)")
    seed = None
    if args.seed_deg is not None:
        if len(args.seed_deg) != nominal.n_joints:
            raise UsageError(f"--seed-deg: give {nominal.n_joints} joint values, got {len(args.seed_deg)}")
        seed = np.deg2rad(args.seed_deg)
    try:
        program = read_program(args.program)
        before = marked(program.text.splitlines())
        refuse_marked(args, args.program, before)
        result = compensate_program(program, nominal, calibrated, default_tcp_mm=tcp_mm, seed_rad=seed,
                                    tool_map=tools)
    except ProgramError as exc:
        raise UsageError(str(exc)) from None
    failed = result.failed
    written = not failed or args.allow_partial
    if written:
        try:
            text = rewrite(program.text, result.replacements)
            ending = "" if not text or text.endswith(("\n", "\r")) else "\n"
            with open(args.out, "wb") as f:  # the marker last: every line keeps its number
                f.write(encode(f"{text}{ending}# {MARK} {mark(args, nominal)}\n"))
        except OSError as exc:
            raise UsageError(f"-o {args.out}: cannot write: {exc.strerror or exc}") from None
    counts = Counter(o.status for o in result.per_target)
    n, done = len(result.per_target), counts.pop(COMPENSATED, 0)
    left = ", ".join(f"{k} {s}" for s, k in sorted(counts.items()))
    error = None
    if not written:
        error = (f"{counted(len(failed), 'literal target')} could not be compensated (listed); nothing written to "
                 f"{args.out}: --allow-partial writes the program with them left as written")
    if args.json:
        doc = {"program": str(args.program), "out": str(args.out), "written": written, "targets": n,
               "compensated": done, "not_compensated": dict(sorted(counts.items())), "compensated_before": before,
               "nominal_model": nominal.name, "seconds": result.seconds,
               "tool": _tool_doc(tools, tcp_mm, tools.to_model(tcp_mm))}
        tail = f', "error": {json.dumps({"code": 1, "message": error})}' if error else ""
        # json.dumps of the whole document, its report written a thousand targets at a time (a long
        # program's report as one list of dicts and one string would double the command's memory)
        sys.stdout.write(json.dumps(doc)[:-1] + ', "report": [')
        for k in range(0, n, 1000):
            sys.stdout.write((", " if k else "") + ", ".join(json.dumps(o.as_dict())
                                                            for o in result.per_target[k:k + 1000]))
        sys.stdout.write(f"]{tail}}}\n")
    else:
        for o in result.per_target:
            t = o.target
            which = " " + t.role.removeprefix("pose_") if t.call == "movec" else ""  # movec's via and to
            where = f"{args.program}:{t.line}: {t.call}{which} ({t.kind})"
            if o.status == COMPENSATED:
                within = "" if o.bound_mm is None else f", lands within {o.bound_mm:.3f} mm (95 %)"
                print(f"{where}: ok, moved {o.shift_mm:.4f} mm and {o.turn_deg:.4f} deg, joints by up to "
                      f"{o.joint_deg:.4f} deg{within}")
            else:
                print(f"{where}: {o.status}: {o.reason}")
        print(f"compensated {done} of {counted(n, 'target')} of {args.program} with {args.robot} (nominal: "
              f"{nominal.name}) in {result.seconds:.2f} s" + (f"; not compensated: {left}" if left else "")
              + (f"; written to {args.out}" if written else "; nothing written"))
        bounds = [o.bound_mm for o in result.per_target if o.bound_mm is not None]
        print(_tool_text(tools, tcp_mm, tools.to_model(tcp_mm),
                         {"max": max(bounds), "mean": sum(bounds) / len(bounds)} if bounds else None))
    large = [o for o in result.per_target if o.status == COMPENSATED and o.joint_deg > args.max_correction_deg]
    for o in large[:SHOWN_ROWS]:
        print_progress(f"{args.program}:{o.target.line}: warning: compensated, but the joints move by "
                       f"{o.joint_deg:.3g} deg (above --max-correction-deg {args.max_correction_deg:g}): check the "
                       "motion into this target")
    if len(large) > SHOWN_ROWS:
        print_progress(f"... {counted(len(large) - SHOWN_ROWS, 'more target')} with a correction above "
                       f"{args.max_correction_deg:g} deg (joint_deg in the report)")
    if n == 0:
        print_progress(f"{args.program}: warning: no movej, movel, movep or movec target in the program: nothing "
                       "was compensated (is it the right file?)")
    if before is not None:
        print_progress(f"{args.program}: warning: compensated before ({before}); --force compensated it again: "
                       "every target moved a second time")
    if error:
        print_progress(f"error: {error}")
        return 1
    return 0
