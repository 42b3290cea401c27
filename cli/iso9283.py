"""``cellcal iso9283``: pose accuracy and repeatability (and distance accuracy) per ISO 9283.

MEASURED.csv is a measurement file (the joints the robot was commanded, the measured
target positions in the instrument frame) with two more columns: ``pose`` (P1 .. P5,
``solvers.identification.iso9283``) and ``cycle``. The command position of each row is where the
``--robot`` model puts the target at the commanded joints (its geometry, effects,
instrument frame and target offset): for a nominal model that is the programmed point,
for a calibrated model what the calibration says the robot reaches, and for joints
from ``cellcal compensate`` the point the program asked for.
"""
from __future__ import annotations

import json

import numpy as np

from cellcal.config.model_files import load_calibrated
from cellcal.measurements.reader import read_measurements
from cellcal.measurements.table import repeated_measurements
from cellcal.solvers.analysis.effects import Context, approach_directions
from cellcal.solvers.identification.iso9283 import DISTANCE_PAIR, MIN_CYCLES, POSES, STANDARD_CYCLES, characteristics
from cellcal.cli.common import ReportError, UsageError, counted, print_progress, writable_folder


def add_parser(sub):
    p = sub.add_parser(
        "iso9283", help="pose accuracy AP and repeatability RP at the cube points, per ISO 9283",
        description="Pose accuracy (AP, clause 7.2.1) and pose repeatability (RP, clause 7.2.2) of ISO 9283:1998 "
                    "at each test pose from repeated cycles, and distance accuracy and repeatability (AD, RD, "
                    "clause 7.4) between P2 and P4 where both were measured in the same cycles. The command "
                    "position of a row is the --robot model's prediction at its commanded joints.")
    p.add_argument("--robot", required=True, metavar="MODEL.yaml",
                   help="robot model file (calibrated or nominal, with its instrument frame) or shipped name")
    p.add_argument("--data", required=True, metavar="MEASURED.csv",
                   help="measurement CSV with columns pose (P1 .. P5) and cycle")
    p.add_argument("--report", metavar="DIR", help="write plots and a readable page here")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(func=run)


def check_test(data_path, table, pose, cycle) -> list[str]:
    """Refuse (UsageError naming file, line and column) what ISO 9283's definitions exclude, and
    return warnings for what it allows but does not call the standard's test: each row is one
    of the test poses P1 .. P5 (the cube's points), in a cycle numbered by a whole number, each
    pose once per cycle (x_j is the position attained in cycle j), at least MIN_CYCLES cycles per
    pose (with two, S_l is 0 by construction); fewer than the standard's 30 cycles, a test pose
    left out, or one measured position appearing twice are warned of."""
    for k, p in enumerate(map(str, pose)):
        if p not in POSES:
            raise UsageError(f"{data_path}:{table.line[k]}: column 'pose': {p!r} is not a test pose of ISO 9283 "
                             f"({', '.join(POSES)}: the centre of the test cube and four points on its diagonals)")
    for k, c in enumerate(map(str, cycle)):
        if not (c.isascii() and c.isdigit()):
            raise UsageError(f"{data_path}:{table.line[k]}: column 'cycle': {c!r} is not a cycle number "
                             "(a whole number: the j-th run through the test poses)")
    seen: dict[tuple[str, int], int] = {}
    for k, key in enumerate(zip(map(str, pose), (int(c) for c in cycle))):
        if key in seen:
            raise UsageError(f"{data_path}:{table.line[k]}: pose {key[0]} in cycle {key[1]} again (first at line "
                             f"{seen[key]}): ISO 9283 measures each pose once per cycle")
        seen[key] = int(table.line[k])
    counts = {p: int(np.sum(pose == p)) for p in POSES if np.any(pose == p)}
    few = [p for p, n in counts.items() if n < MIN_CYCLES]
    if few:
        raise UsageError(f"{data_path}: pose {few[0]} is measured in {counted(counts[few[0]], 'cycle')}; "
                         f"repeatability needs at least {MIN_CYCLES} (with two, both positions lie equally far "
                         "from their barycentre and S_l is 0 whatever the robot does)")
    warnings = []
    least = min(counts, key=counts.get)
    if counts[least] < STANDARD_CYCLES:
        measured = (f"{counts[least]} cycles" if len(set(counts.values())) == 1 else
                    f"as few as {counts[least]} cycles ({least})")
        warnings.append(f"{measured}; ISO 9283 asks for {STANDARD_CYCLES} cycles for pose accuracy and "
                        "repeatability, so these AP and RP are not the standard's figures")
    missing = [p for p in POSES if p not in counts]
    if missing:
        warnings.append(f"no rows for {', '.join(missing)}: the standard's test visits all of {', '.join(POSES)}")
    repeated = repeated_measurements(table)
    if repeated:
        first, again = repeated[0]
        warnings.append(f"{counted(len(repeated), 'measured position')} repeat earlier ones exactly (line {again} "
                        f"repeats line {first}): "
                        "a copied measurement is no new cycle; the standard deviations S_l (and so RP) come out "
                        "too small")
    return warnings


def evaluate(robot, data_path, warnings: list[str] | None = None):
    """(model name, pose labels, cycles, commanded (N, 3), attained (N, 3), poses, distance) of one data set.
    What the standard allows but does not call its test goes to `warnings` (a list), else to stderr."""
    model = load_calibrated(robot)
    table = read_measurements(data_path, model.model.n_joints)
    for column in ("pose", "cycle"):
        if column not in table.extra:
            raise UsageError(f"{data_path}: missing column {column!r} (ISO 9283 data name each row's test pose "
                             "P1 .. P5 and its cycle)")
    pose = np.array([p.strip() for p in table.extra["pose"]])
    cycle = np.array([c.strip() for c in table.extra["cycle"]])
    for warning in check_test(data_path, table, pose, cycle):
        if warnings is None:
            print_progress(f"warning: {data_path}: {warning}")
        else:
            warnings.append(warning)
    cycle = cycle.astype(int)
    names = list(model.target_names)
    index = []
    for t in table.target_names:
        if t in names:
            index.append(names.index(t))
        elif len(table.target_names) == 1:
            index.append(0)  # one target measured: the model's first target offset
        else:
            raise UsageError(f"{data_path}: target {t!r} has no offset in {robot} ({', '.join(names)})")
    ctx = Context(direction=approach_directions(table.q_rad), payload_kg=table.payload_kg)
    commanded = model.predict(table.q_rad, np.array(index)[table.target], ctx)
    poses, distance = characteristics(pose, cycle, commanded, table.xyz_mm)
    return model.model.name, pose, cycle, commanded, table.xyz_mm, poses, distance


def as_json(poses, distance) -> dict:
    out = {"poses": [{"pose": p.pose, "n": p.n, "AP_mm": p.ap_mm, "AP_x_mm": p.ap_xyz_mm[0],
                      "AP_y_mm": p.ap_xyz_mm[1], "AP_z_mm": p.ap_xyz_mm[2], "RP_mm": p.rp_mm,
                      "l_bar_mm": p.l_bar_mm, "S_l_mm": p.s_l_mm} for p in poses],
           "AP_max_mm": max(p.ap_mm for p in poses), "RP_max_mm": max(p.rp_mm for p in poses)}
    if distance is not None:
        out["distance"] = {"poses": list(distance.poses), "n": distance.n, "D_c_mm": distance.commanded_mm,
                           "AD_mm": distance.ad_mm, "RD_mm": distance.rd_mm}
    return out


def as_text(title: str, poses, distance) -> str:
    lines = [title, "", f"{'pose':6s}{'n':>5s}{'AP mm':>10s}{'AP_x':>9s}{'AP_y':>9s}{'AP_z':>9s}{'RP mm':>10s}"]
    for p in poses:
        lines.append(f"{p.pose:6s}{p.n:5d}{p.ap_mm:10.4f}{p.ap_xyz_mm[0]:9.4f}{p.ap_xyz_mm[1]:9.4f}"
                     f"{p.ap_xyz_mm[2]:9.4f}{p.rp_mm:10.4f}")
    if distance is not None:
        lines.append(f"\ndistance {distance.poses[0]}-{distance.poses[1]} ({distance.n} cycles, commanded "
                     f"{distance.commanded_mm:.3f} mm): AD {distance.ad_mm:+.4f} mm, RD {distance.rd_mm:.4f} mm")
    else:
        lines.append(f"\ndistance accuracy: not computed ({DISTANCE_PAIR[0]} and {DISTANCE_PAIR[1]} are not both "
                     "measured in two or more common cycles)")
    return "\n".join(lines)


def run(args) -> int:
    if args.report:  # before reading anything: a folder that cannot take the report is said at once
        writable_folder(args.report, "--report")
    warnings: list[str] = []
    name, pose, cycle, commanded, attained, poses, distance = evaluate(args.robot, args.data, warnings)
    title = f"cellcal iso9283: {name} ({args.robot}), {args.data}"
    text = as_text(title, poses, distance) + "".join(f"\nwarning: {w}" for w in warnings)
    if args.json:
        print(json.dumps({**as_json(poses, distance), "warnings": warnings}), flush=True)
    else:
        print(text, flush=True)
    if args.report:
        from cellcal.reports.iso9283 import write_report

        try:
            page = write_report(args.report, [(str(args.robot), pose, commanded, attained, poses, distance)], text)
        except OSError as exc:
            raise ReportError(f"--report {args.report}: cannot write the report there: {exc.strerror or exc}; "
                              "the result above stands") from None
        print_progress(f"report written to {page}")
    return 0
