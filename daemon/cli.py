"""The ``cellcal`` command line (contract: the project's spec/cli.md).

Exit status: 0 success, 2 bad usage or bad input (one clear message), 1 a failure
of the cell or the computation. With ``--json`` stdout carries one JSON object and
nothing else; progress goes to stderr.
"""
from __future__ import annotations

import argparse
import json
import sys

import numpy as np
from threadpoolctl import threadpool_limits

from ..config.reader import ConfigError
from ..drivers.interfaces import DeviceError
from ..routines.base import RoutineError
from ..config.robot_files import load_robot
from ..routines.dataset import DatasetError, MeasurementTable, check_joint_limits, read_measurements
from ..solvers.identify import LOSSES, REGULARIZE, IdentifyOptions, identify
from . import analyze_cmd, compensate_cmd, daemon_cmd, demo_cmd, importers, iso9283_cmd, model_out, run_cmd, sim_campaign, sim_cell
from .cli_common import ReportError, UsageError, check_folds, check_positive, print_progress
from .report import identification_json, identification_text


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # argparse's own errors: exit 2 with one line
        self.exit(2, f"{self.prog}: error: {message}\n")


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


def cmd_identify(args) -> int:
    model = load_robot(args.robot)
    table = read_measurements(args.data, model.n_joints)
    validate = read_measurements(args.validate, model.n_joints) if args.validate else None
    cal, val = _split(table, validate, args.data)
    if val is not None:
        unknown = sorted(set(val.target_names) - set(cal.target_names))
        if unknown:
            raise UsageError(f"{args.validate or args.data}: target(s) {', '.join(unknown)} do not occur "
                             "in the calibration rows, so their offsets are unknown")
    check_folds(args.folds)
    check_positive("--prior-mm", args.prior_mm)
    check_joint_limits(cal, model.joint_limits, model.name)
    if val is not None:
        check_joint_limits(val, model.joint_limits, model.name)
    bad = sorted(set(args.fix or ()) - set(model.param_names))
    if bad:
        raise UsageError(f"--fix: {', '.join(bad)} not a parameter of {model.name} "
                         f"(parameters: {', '.join(model.param_names)})")
    model_out.check_target(args.write_model)
    n_min = 10
    if len(cal) < n_min:
        raise UsageError(f"{args.data}: {len(cal)} calibration rows; identification needs at least {n_min}")
    options = IdentifyOptions(regularize=args.regularize, loss=args.loss, folds=args.folds,
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
    if args.json:
        print(json.dumps(identification_json(result, obs, val_obs)))
    else:
        print(identification_text(result, obs, val_obs, model.name))
    if args.write_model:
        model_out.write_identified(args, model, result, len(cal), val_obs)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="cellcal", description="Calibration for robot cells.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    p = sub.add_parser("identify", help="kinematic calibration from measured target positions",
                       description="Identify geometric parameters, the instrument -> base transform "
                                   "and the flange -> target offsets from measured positions.")
    p.add_argument("--robot", required=True, metavar="ROBOT",
                   help="robot model file (YAML), or the name of a shipped model such as ur10e")
    p.add_argument("--data", required=True, metavar="CAL.csv", help="measurement CSV")
    p.add_argument("--validate", metavar="VAL.csv",
                   help="measurements to validate on (default: rows of --data marked split=val, if any)")
    p.add_argument("--regularize", choices=REGULARIZE, default="cv",
                   help="cv: L2 prior toward nominal, weight by k-fold cross-validation (default); "
                        "none: least squares over the identifiable parameters")
    p.add_argument("--loss", choices=LOSSES, default="linear",
                   help="robust loss against outliers (default: linear, i.e. least squares)")
    p.add_argument("--folds", type=int, default=5, help="folds of the cross-validation (default 5)")
    p.add_argument("--fix", nargs="+", metavar="PARAM", help="hold these parameters at nominal (e.g. d1 theta1)")
    p.add_argument("--prior-mm", type=float, default=1.0,
                   help="a direction whose estimate would scatter more than this (mm at the target) "
                        "is held at nominal (default 1.0)")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    model_out.add_argument(p)
    p.set_defaults(func=cmd_identify)

    analyze_cmd.add_parser(sub)
    compensate_cmd.add_parser(sub)
    iso9283_cmd.add_parser(sub)
    run_cmd.add_parser(sub)
    daemon_cmd.add_parsers(sub)
    demo_cmd.add_parser(sub)
    importers.add_parser(sub)
    sim_campaign.add_parser(sub)
    sim_campaign.add_sim_data_parser(sub)
    sim_cell.add_parser(sub)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    # the solvers' matrices are small: BLAS threads only contend (several times slower on 2 cores)
    with threadpool_limits(limits=1, user_api="blas"):
        return _run(args)


def _run(args) -> int:
    try:
        return args.func(args)
    except ReportError as exc:  # the result is already on stdout: only the line on stderr
        return _error(args, 2, f"error: {exc}", json_object=False)
    except (DatasetError, ConfigError, UsageError) as exc:
        return _error(args, 2, f"error: {exc}")
    except DeviceError as exc:
        return _error(args, 1, f"device fault, motion stopped: {exc}")
    except RoutineError as exc:
        return _error(args, 1, f"routine failed: {exc}")
    except (ValueError, np.linalg.LinAlgError, RuntimeError, MemoryError) as exc:
        return _error(args, 1, f"computation failed: {exc or type(exc).__name__}")
    except KeyboardInterrupt:
        return _error(args, 1, "interrupted")


def _error(args, code: int, message: str, json_object: bool = True) -> int:
    """One line on stderr; with --json also one error object on stdout (spec/cli.md)."""
    print(f"cellcal: {message}", file=sys.stderr)
    if json_object and getattr(args, "json", False):
        print(json.dumps({"error": {"code": code, "message": message}}))
    return code


if __name__ == "__main__":
    sys.exit(main())
