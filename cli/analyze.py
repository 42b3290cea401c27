"""``cellcal analyze``: what is the rigid model getting wrong?"""
from __future__ import annotations

import json


from cellcal.config.fixture_files import read_fixture
from cellcal.config.robot_files import load_robot
from cellcal.routines.framework.base import jsonable
from cellcal.measurements.reader import joint_velocities, read_measurements
from cellcal.measurements.table import check_joint_limits, overlap_rows, overlap_warning, repeated_warning
from cellcal.solvers.analysis import point_analysis
from cellcal.solvers.analysis.analyze import AnalyzeOptions, Finding, analyze
from cellcal.solvers.analysis.naming import Scored
from cellcal.solvers.analysis.transfer import Transfer, transfer
from cellcal.solvers.identification.identify import LOSSES, IdentificationError
from cellcal.solvers.analysis.effects import CAUSES, Context, approach_directions
from cellcal.solvers.analysis.effects.cyclic_joint_error import order_search
from cellcal.solvers.analysis.physical_sizes import describe
from cellcal.cli import model_out
from cellcal.cli import discriminate as discriminate_cmd
from cellcal.cli import identify_points
from cellcal.cli.common import ReportError, UsageError, print_progress, whole, writable_folder

MIN_MEASUREMENTS = 30
MIN_VALIDATE = 10  # rows of --validate, and at least twice as many coordinates as its frame and targets' unknowns


def add_parser(sub):
    p = sub.add_parser(
        "analyze", help="find, name and size the effect the rigid model misses",
        description="Compare measured data with the rigid kinematic model (geometry calibrated), "
                    "rank the named causes by held-out error, and name one only when it wins clearly; "
                    "otherwise the answer is 'none'.")
    p.add_argument("--robot", required=True, help="robot model file (YAML) or shipped name")
    p.add_argument("--data", required=True, metavar="DATA.csv", help="measurement CSV, rows in measured order")
    p.add_argument("--report", metavar="DIR", help="write plots and a readable page of the finding here")
    p.add_argument("--causes", nargs="+", choices=tuple(CAUSES), default=tuple(CAUSES), metavar="CAUSE",
                   help=f"candidate causes to consider (default: all of {', '.join(CAUSES)})")
    p.add_argument("--folds", type=whole(2, 100), default=5, help="cross-validation folds, 2 .. 100 (default 5)")
    p.add_argument("--loss", choices=LOSSES, default="linear",
                   help="robust loss against gross outliers, as identify's; the held-out scores then leave out "
                        "each model's largest 10%% of errors (default: linear, i.e. least squares)")
    p.add_argument("--validate", metavar="B.csv",
                   help="a second data set (another time, pose set or target): the named effect as fitted on "
                        "--data, with only B's instrument frame and target offsets fitted on B, scored against "
                        "the geometry alone, with how much of B lies inside --data's joint ranges")
    setup = p.add_mutually_exclusive_group()
    setup.add_argument("--same-setup", action="store_true",
                       help="with --validate: B was taken in --data's setup (a test set of the same session: the "
                            "same instrument frame and targets): score it with the frame and target offsets fitted "
                            "on --data, nothing fitted on B (on a small B the refit of --new-setup flatters both "
                            "scores)")
    setup.add_argument("--new-setup", action="store_true",
                       help="with --validate: B was taken in another setup: B's own instrument frame and target "
                            "offsets fitted on B (the default)")
    p.add_argument("--fixture", metavar="FIXTURE.yaml",
                   help="for rows of the point form (sockets, stylus balls; docs/measurements.md): the fixture's "
                        "points, known distances and seating noise, as identify --fixture takes them; the "
                        "baseline is then the fixture calibration, with each point refit in every fold")
    p.add_argument("--strict-sizes", action="store_true",
                   help="name no cause whose fitted size is beyond what arms of the robot's class show, however "
                        "clear its lead (then: an effect, cause undecided). Default: such a lead is set aside "
                        "when an explanation of plausible size comes within the 8%% margin, else named with its "
                        "size given as the reason against it")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    model_out.add_argument(p, analyze=True)
    discriminate_cmd.add_arguments(p)
    p.set_defaults(func=run)


def _context(table) -> Context:
    return Context(direction=approach_directions(table.q_rad), t_s=table.t_s, temp_c=table.temp_c,
                   payload_kg=table.payload_kg, dq_rad_s=joint_velocities(table))


def _scored(s: Scored) -> dict:
    out = {"cause": s.cause, "where": s.where, "label": s.label, "heldout_mean_mm": s.heldout_mean_mm}
    if s.judged is not None:  # its linearised size against the typical maximum of the robot's class
        out["plausibility"] = s.judged.json()
        if not s.judged.plausible:
            out["against"] = f"it {s.judged.text()}"
    return out


def finding_json(f: Finding, n: int) -> dict:
    out = {
        "cause": f.cause,
        "where": f.where,
        "magnitude": f.magnitude,
        "baseline": {"heldout_mean_mm": f.baseline.heldout_mean_mm},
        "extended": {"heldout_mean_mm": f.extended.heldout_mean_mm,
                     **({"prior_weights": list(f.extended.prior_weights)} if f.extended.prior_weights else {})},
        "gain_pct": f.gain_pct,
        "margin_pct": 100.0 * f.margin,
        "candidates": [_scored(c) for c in f.candidates],
        "notes": list(f.notes),
        **discriminate_cmd.tie_json(f),
        "undecided": _undecided_json(f),
        "decided_by": list(f.decided_by),
        "robot_class": f.robot_class.json() if f.robot_class is not None else None,
        "n": n,
        "seconds": f.seconds,
    }
    out.update(_coverage_json(f))
    out["heldout_trimmed_pct"] = 100.0 * f.baseline.trim  # largest errors each score leaves out (robust loss)
    if f.second is not None:
        first_pct, second_pct = f.shares_pct
        out["second"] = {**_scored(f.second), "heldout_share_pct": second_pct}
        out["both"] = {"label": f.both.label, "heldout_mean_mm": f.both.heldout_mean_mm,
                       "magnitude": f.both.magnitude,
                       "heldout_shares_pct": {f.extended.label: first_pct, f.second.label: second_pct}}
    return out


def validate_json(v: Transfer) -> dict:
    """The finding tried on the --validate data set."""
    return {"baseline_mean_mm": v.baseline_mean_mm, "extended_mean_mm": v.extended_mean_mm, "gain_pct": v.gain_pct,
            "rows": len(v.baseline_errors_mm), "effect": v.carried or None,
            "setup": "same" if v.same_setup else "new",
            "coverage": {"per_joint": list(v.coverage_per_joint), "all_joints": v.coverage_all},
            "note": v.note}


def validate_text(v: Transfer, path: str) -> list[str]:
    how = ("the same setup: frame and target offsets as fitted here, nothing fitted on it" if v.same_setup else
           "frame and target offsets fitted on it, everything else as fitted here")
    lines = [f"validate on {path} ({len(v.baseline_errors_mm)} measurements; {how}):"]
    if v.extended_errors_mm is None:
        lines.append(f"  geometry only {v.baseline_mean_mm:.4f} mm mean; {v.note}")
    else:
        lines.append(f"  geometry only {v.baseline_mean_mm:.4f} mm mean, with {v.carried} "
                     f"{v.extended_mean_mm:.4f} mm (gain {v.gain_pct:.1f}%)")
    lines.append(f"  inside this data set's joint ranges: {100 * v.coverage_all:.0f}% of its rows on every joint; "
                 "per joint " + ", ".join(f"{j + 1}: {100 * c:.0f}%" for j, c in enumerate(v.coverage_per_joint)))
    return lines


def _read_validate(path: str, model, cal_table):
    """The --validate data set as observations and context, and how many of its rows are poses of the
    calibration data (:func:`overlap_rows`, said on stderr); one message for what it lacks."""
    table = read_measurements(path, model.n_joints)
    check_joint_limits(table, model.joint_limits, model.name)
    obs = table.observations()  # refuses point-form rows: the effect is scored on measured positions
    unknowns = 6 + 3 * len(obs.target_names)
    if len(obs) < MIN_VALIDATE or 3 * len(obs) < 2 * unknowns:
        raise UsageError(f"{path}: {len(obs)} measurements; --validate needs at least "
                         f"{max(MIN_VALIDATE, -(-2 * unknowns // 3))} to fit its own frame and "
                         f"{len(obs.target_names)} target offset(s) and still test the effect")
    overlap = overlap_rows(cal_table, table)
    if (warning := overlap_warning(cal_table, table, overlap)) is not None:
        print_progress(f"warning: {warning}")
    return obs, _context(table), overlap


def _undecided_json(f: Finding) -> dict | None:
    """An effect whose cause these data cannot decide: its size, and the experiment that decides (else None)."""
    if f.undecided is None:
        return None
    return {"gain_pct": 100.0 * (1.0 - f.undecided.heldout_mean_mm / f.baseline.heldout_mean_mm),
            "heldout_mean_mm": f.undecided.heldout_mean_mm,
            "causes": [t.cause for t in f.indistinguishable], "experiment": f.decide_by}


def _spectra(f: Finding) -> dict | None:
    """The cyclic order scan of this analysis, when the cause was scored."""
    return next((t.extra["spectra"] for c in f.candidates for t in c.terms if "spectra" in t.extra), None)


def _coverage_json(f: Finding) -> dict:
    """Joint angles the data cover, the cyclic orders scanned, and the fitted effect for later use."""
    out = {"joint_coverage_deg": {str(j + 1): list(r) for j, r in enumerate(f.joint_range_deg)}}
    if (spectra := _spectra(f)) is not None:
        out["cyclic_order_search"] = order_search(spectra)
    if f.extended.details is not None:
        out["effect"] = f.extended.details
    return out


def _coverage_text(f: Finding) -> list[str]:
    lines = []
    for err in (f.extended.details or {}).get("errors", []):
        cover = ", ".join(f"{lo:+.1f}..{hi:+.1f}" for lo, hi in err["coverage_deg"])
        what = f"orders {err['orders']}" if "orders" in err else f"periodic spline, {err['spline_knots']} knots"
        lines.append(f"  joint {err['joint']}: {what}, known over {cover} deg")
    if lines:
        lines.append(f"  {f.extended.details['outside_coverage']}")
    if (spectra := _spectra(f)) is not None:
        search = order_search(spectra)
        lines.append("cyclic orders scanned: " + ", ".join(f"joint {j} 1-{v['orders'][1]}"
                                                          for j, v in search["joints"].items()))
        lines.append(f"  ({search['rule']})")
    lines.append("joint coverage (deg): " + ", ".join(f"{j + 1}: {lo:+.1f}..{hi:+.1f}"
                                                      for j, (lo, hi) in enumerate(f.joint_range_deg)))
    return lines


def finding_text(f: Finding, robot: str, n: int, not_scored=(), validation=None) -> str:
    lines = [f"cellcal analyze: {robot}, {n} measurements", ""]
    if f.undecided is not None:
        gain = 100.0 * (1.0 - f.undecided.heldout_mean_mm / f.baseline.heldout_mean_mm)
        lines.append(f"finding: an effect, cause undecided -- the best explanation gains {gain:.1f}% on held-out "
                     f"data ({f.undecided.heldout_mean_mm:.4f} mm), but these data cannot tell apart "
                     "the explanations below (cause: none)")
        if f.decide_by:  # (none when the only explanation that gains was set aside as implausible)
            lines.append(f"  experiment that decides: {f.decide_by}")
    elif f.cause == "none" and f.indistinguishable:
        lines.append("finding: none -- these data cannot tell apart the explanations below")
    elif f.cause == "none":
        lines.append("finding: none -- no candidate beats the geometric model clearly on held-out data")
    else:
        where = ", ".join(f"{k} {v}" for k, v in f.where.items())
        lines.append(f"finding: {f.cause} ({where})")
        for k, v in f.magnitude.items():
            lines += describe(v) if isinstance(v, list) else [f"  {k:32s} {v:.6g}"]
    with_effect = (f"with the effect {f.extended.heldout_mean_mm:.4f} mm (gain {f.gain_pct:.1f}%)"
                   if f.undecided is None else
                   f"with its best explanation {f.undecided.heldout_mean_mm:.4f} mm, cause undecided")
    lines.append(f"held-out mean error: geometry only {f.baseline.heldout_mean_mm:.4f} mm, {with_effect}"
                 + (f", each without its largest {100 * f.baseline.trim:.0f}% (robust loss)"
                    if f.baseline.trim else ""))
    if f.undecided is None and f.extended.prior_weights:
        lines.append("  the effect's prior (no effect) weighed inside each fold's training rows, relative to each "
                     "column's squared norm: " + ", ".join(f"{w:g}" for w in f.extended.prior_weights))
    lines += _coverage_text(f)
    if f.second is not None:
        first_pct, second_pct = f.shares_pct
        lines.append(f"second effect: {f.second.label}; both fitted: {f.both.heldout_mean_mm:.4f} mm held-out "
                     f"(of the gain over geometry alone {first_pct:.0f}% is the first's, "
                     f"{second_pct:.0f}% the second's)")
    lines += [f"  note: {note}" for note in (*f.notes, *not_scored)]
    if f.grounds and not f.indistinguishable:  # with a tie, its lines say the grounds
        lines.append(f"  grounds: {f.grounds}")
    if f.decided_by:
        lines.append(f"  decided by: {', '.join(f.decided_by)}"
                     + (f" (robot class {f.robot_class.name}: {f.robot_class.reason})" if f.robot_class else ""))
    lines += discriminate_cmd.tie_lines(f)
    if validation is not None:
        lines += validate_text(*validation)
    lines += ["", "candidates (held-out mean error, mm):"]
    for c in f.candidates[:10]:
        against = f"  -- implausible: {c.judged.text()}" if c.judged is not None and not c.judged.plausible else ""
        lines.append(f"  {c.heldout_mean_mm:8.4f}  {c.label}{against}")
    if len(f.candidates) > 10:
        lines.append(f"  ... {len(f.candidates) - 10} more (--json lists all)")
    lines.append(f"\n{f.seconds:.1f} s")
    return "\n".join(lines)


def run(args) -> int:
    if (args.same_setup or args.new_setup) and not args.validate:
        raise UsageError(f"--{'same' if args.same_setup else 'new'}-setup: says how --validate's data set is scored; "
                         "give --validate as well")
    model_out.check_target(args.write_model)
    if args.report:  # before the analysis: a folder that cannot take the report is said at once
        writable_folder(args.report, "--report")
    discriminate_cmd.check_arguments(args)
    model = load_robot(args.robot)
    table = read_measurements(args.data, model.n_joints)
    if (warning := repeated_warning(table)) is not None:
        print_progress(f"warning: {warning}")
    check_joint_limits(table, model.joint_limits, model.name)
    model_out.drawn_targets(args, table.target_names)  # refused now rather than after the analysis
    if len(table) < MIN_MEASUREMENTS:
        raise UsageError(f"{args.data}: {len(table)} measurements; the analysis needs at least {MIN_MEASUREMENTS}")
    fixture = read_fixture(args.fixture) if args.fixture else None
    points = fixture is not None or table.is_point.any()
    if points:  # sockets or balls: the fixture calibration is the baseline (solvers.analysis.point_analysis)
        fixture_fit, point_data = identify_points.fixture_fit_for_analysis(args, model, table, fixture)
        obs = point_analysis.observations(fixture_fit, point_data)
    else:
        obs = table.observations()
    obs_b, ctx_b, overlap = _read_validate(args.validate, model, table) if args.validate else (None, None, 0)
    if obs_b is not None and args.same_setup:
        unknown = sorted(set(obs_b.target_names) - set(obs.target_names))
        if unknown:
            raise UsageError(f"--same-setup: {args.validate} measures target(s) {', '.join(unknown)} that {args.data} "
                             "does not, so the setup gives them no offset; drop --same-setup to fit them on it")
    ctx = _context(table)
    requested = tuple(dict.fromkeys(args.causes))
    unscorable = {c: why for c in requested if (why := CAUSES[c].unscorable(model, ctx))}
    if len(unscorable) == len(requested):
        raise UsageError(f"{args.data}: none of the requested causes can be scored on these data: "
                         + "; ".join(f"{c} {why}" for c, why in unscorable.items()))
    not_scored = [f"{c} not scored: {why}" for c, why in unscorable.items()]
    for note in not_scored:
        print_progress(note)
    causes = tuple(c for c in requested if c not in unscorable)
    finding = analyze(model, obs, ctx, AnalyzeOptions(folds=args.folds, causes=causes, loss=args.loss,
                                                      strict_sizes=args.strict_sizes),
                      progress=print_progress,
                      geometry=point_analysis.geometry(fixture_fit, point_data, obs) if points else None)
    validation = None
    if obs_b is not None:
        try:
            validation = transfer(model, finding, obs, obs_b, ctx_b, args.loss, same_setup=args.same_setup)
        except IdentificationError as exc:
            raise IdentificationError(f"--validate {args.validate}: {exc}") from None  # exit 1: B's data are wrong
    text = finding_text(finding, model.name, len(obs), not_scored,
                        None if validation is None else (validation, args.validate))
    experiment = discriminate_cmd.run_design(args, finding, ctx, model)
    if experiment and experiment["poses"]:
        text += f"\n\nexperiment: {experiment['summary']}\nposes written to {experiment['file']}"
    # the finding first: a report that cannot be written must not lose it
    if points:
        g = finding.scorer.geometric_fit
        point_note = (f"point form: the baseline is the fixture calibration of {len(point_data.points)} points in "
                      f"{len({s for s, _ in point_data.points})} setups, each point refit in every fold"
                      + (f"; held at that calibration (only the fixture's distances fix them): "
                         f"{', '.join(g.held_without_distances)}" if g.held_without_distances else ""))
        not_scored = [point_note] + not_scored
        text = point_note + "\n" + text
    if args.json:
        out = finding_json(finding, len(obs))
        out["notes"] = out["notes"] + not_scored
        if points:
            out["form"] = "point"
            out["point_form"] = {"setups": len({s for s, _ in point_data.points}), "points": len(point_data.points),
                                 "contact": fixture_fit.options.stylus_radius_mm is not None,
                                 "held_without_distances": list(finding.scorer.geometric_fit.held_without_distances)}
        out["not_scored"] = {c: why for c, why in unscorable.items()}
        if experiment is not None:
            out["discriminate"] = experiment
        if validation is not None:
            out["validate"] = {**validate_json(validation), "overlap_rows": overlap}
        print(json.dumps(out, default=jsonable), flush=True)
    else:
        print(text, flush=True)
    if args.write_model:
        model_out.write_finding(args, model, obs, finding)
    if args.report:
        from cellcal.reports.analysis import write_report  # matplotlib loads only when a report is asked for

        try:
            page = write_report(args.report, model, obs, finding, text, validation)
        except OSError as exc:
            raise ReportError(f"--report {args.report}: cannot write the report there: "
                              f"{exc.strerror or exc}; the finding above stands") from None
        print_progress(f"report written to {page}")
    return 0
