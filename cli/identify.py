"""``cellcal identify``: kinematic calibration from measured target positions."""
from __future__ import annotations

import json

import numpy as np

from cellcal.cli import identify_points, model_out
from cellcal.cli.common import UsageError, number, print_progress, whole
from cellcal.config.fixture_files import read_fixture
from cellcal.config.robot_files import load_robot
from cellcal.measurements.reader import read_measurements
from cellcal.measurements.table import (MeasurementTable, check_joint_limits, overlap_rows, overlap_warning,
                                        repeated_warning)
from cellcal.reports.identification import identification_json, identification_text
from cellcal.solvers.identification.identify import LOSSES, REGULARIZE, IdentifyOptions, identify
from cellcal.solvers.identification.kinematic_fit import register


def _split(table: MeasurementTable, validate: MeasurementTable | None, path: str):
    """Calibration and validation rows: --validate file, else the split column."""
    if validate is not None:
        if table.split is not None and np.any(table.split == "val"):
            raise UsageError(f"{path}: has rows marked split=val and --validate was given too; use one")
        return table, validate
    if table.split is None or not np.any(table.split == "val"):
        return table, None
    cal = table.rows(table.split == "cal")
    if len(cal) == 0:
        raise UsageError(f"{path}: every row is marked split=val; nothing is left to calibrate on")
    return cal, table.rows(table.split == "val")


def run(args) -> int:
    model = load_robot(args.robot)
    fixture = read_fixture(args.fixture) if args.fixture else None
    table = read_measurements(args.data, model.n_joints)
    validate = read_measurements(args.validate, model.n_joints) if args.validate else None
    for data in (table, validate):
        if data is not None and (warning := repeated_warning(data)) is not None:
            print_progress(f"warning: {warning}")
    cal, val = _split(table, validate, args.data)
    if (args.same_setup or args.new_setup) and val is None:
        raise UsageError(f"--{'same' if args.same_setup else 'new'}-setup: says how validation rows are scored; give "
                         "--validate (or rows marked split=val)")
    if val is not None:
        unknown = sorted(set(val.target_names) - set(cal.target_names))
        if unknown:
            raise UsageError(f"{args.validate or args.data}: target(s) {', '.join(unknown)} do not occur "
                             "in the calibration rows, so their offsets are unknown")
    check_joint_limits(cal, model.joint_limits, model.name)
    if val is not None:
        check_joint_limits(val, model.joint_limits, model.name)
    bad = sorted(set(args.fix or ()) - set(model.param_names))
    if bad:
        raise UsageError(f"--fix: {', '.join(bad)} not a parameter of {model.name} "
                         f"(parameters: {', '.join(model.param_names)})")
    model_out.check_target(args.write_model)
    model_out.drawn_targets(args, cal.target_names)  # refused now rather than after the fit
    n_min = 10
    if len(cal) < n_min:
        raise UsageError(f"{args.data}: {len(cal)} calibration rows; identification needs at least {n_min}")
    overlap = 0
    if val is not None:  # validation rows that are calibration rows score the fit in-sample: said first
        overlap = overlap_rows(cal, val)
        if (warning := overlap_warning(cal, val, overlap)) is not None:
            print_progress(f"warning: {warning}")
    if fixture is not None or any(t is not None and t.is_point.any() for t in (cal, val)):
        # the point form: fixtures as the instrument
        if args.same_setup or args.new_setup:
            raise UsageError(f"--{'same' if args.same_setup else 'new'}-setup: point-form rows are validated with "
                             "each setup's points as calibrated and the points of a setup the calibration never saw "
                             "placed anew; the option is for measured positions")
        return identify_points.run(args, model, cal, val, fixture, overlap)
    options = IdentifyOptions(regularize=args.regularize or "cv", loss=args.loss, folds=args.folds,
                              fixed=tuple(args.fix or ()), prior_mm=args.prior_mm)
    obs = cal.observations()
    val_obs = None
    if val is not None:
        # validation rows use the calibration's target numbering
        index = {t: i for i, t in enumerate(cal.target_names)}
        val_obs = val.observations()
        val_obs = type(val_obs)(val_obs.q, val_obs.xyz_mm,
                                np.array([index[val.target_names[t]] for t in val.target]),
                                cal.target_names)
    result = identify(model, obs, options, progress=print_progress)
    val_x = None  # --new-setup: the validation rows' own frame and target offsets, kinematics as calibrated
    if val_obs is not None and args.new_setup:
        val_x = tuple(register(result.layout, x, val_obs).x for x in (result.x, result.x_nominal))
    if args.json:
        doc = identification_json(result, obs, val_obs, val_x)
        if "validate" in doc:
            doc["validate"]["overlap_rows"] = overlap
        print(json.dumps(doc))
    else:
        print(identification_text(result, obs, val_obs, model.name, val_x))
    if args.write_model:
        model_out.write_identified(args, model, result, len(cal), val_obs, obs, None if val_x is None else val_x[0])
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser("identify", help="kinematic calibration from measured target positions",
                       description="Identify geometric parameters, the instrument -> base transform "
                                   "and the flange -> target offsets from measured positions.")
    p.add_argument("--robot", required=True, metavar="ROBOT",
                   help="robot model file (YAML), or the name of a shipped model such as ur10e")
    p.add_argument("--data", required=True, metavar="CAL.csv", help="measurement CSV")
    p.add_argument("--fixture", metavar="FIXTURE.yaml",
                   help="the fixture's points and the known distances between them, for rows of the point form "
                        "(a point column instead of x_mm, y_mm, z_mm; docs/measurements.md)")
    p.add_argument("--validate", metavar="VAL.csv",
                   help="measurements to validate on (default: rows of --data marked split=val, if any)")
    setup = p.add_mutually_exclusive_group()
    setup.add_argument("--same-setup", action="store_true",
                       help="validation rows taken in the calibration's setup (the default): scored with the "
                            "calibrated instrument frame and target offsets, nothing fitted on them")
    setup.add_argument("--new-setup", action="store_true",
                       help="validation rows taken in another setup: their own instrument frame and target offsets "
                            "fitted on them (kinematics as calibrated), as analyze --validate does by default")
    p.add_argument("--regularize", choices=REGULARIZE,
                   help="cv: L2 prior toward nominal, weight by k-fold cross-validation (default); "
                        "none: least squares over the identifiable parameters (tracker rows only: the point form "
                        "is fitted by least squares with --prior-mm's prior)")
    p.add_argument("--force", action="store_true",
                   help="with --write-model: write the model even when the fit fails its fixture's known distances "
                        "(status 1 all the same)")
    p.add_argument("--loss", choices=LOSSES, default="linear",
                   help="robust loss against outliers (default: linear, i.e. least squares)")
    p.add_argument("--folds", type=whole(2, 100), default=5, help="folds of the cross-validation, 2 .. 100 (default 5)")
    p.add_argument("--fix", nargs="+", metavar="PARAM", help="hold these parameters at nominal (e.g. d1 theta1)")
    p.add_argument("--prior-mm", type=number(0.0, 1000.0, above=True, unit="mm"), default=1.0,
                   help="a direction whose estimate would scatter more than this (mm at the target) "
                        "is held at nominal (above 0, at most 1000; default 1.0)")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    model_out.add_argument(p)
    p.set_defaults(func=run)
