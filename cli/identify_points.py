"""``cellcal identify`` on data of the point form: calibration from the cell's own fixtures.

Rows that name the fixed point the target sat at (``point``, ``setup``) instead of a
measured position, with the fixture's known distances from ``--fixture FIXTURE.yaml``
(``config.fixture_files``), are solved by ``solvers.fixtures.fixture_identify``. Everything that
makes the data unusable is refused here, before any computation, with one message naming
the file, the line and the column (or the fixture file and its key).
"""
from __future__ import annotations

import json

import numpy as np

from cellcal.cli import model_out
from cellcal.cli.common import UsageError, print_progress
from cellcal.config.fixture_files import Fixture, FixtureError
from cellcal.measurements.table import DatasetError, MeasurementTable
from cellcal.reports.fixture_identification import fixture_json, fixture_text
from cellcal.solvers.compensation.calibrated_model import from_fit
from cellcal.solvers.fixtures.fixture_identify import MIN_ROWS_PER_POINT, identify_points, refit_points
from cellcal.solvers.fixtures.point_problem import FixtureOptions, PointData
from cellcal.solvers.identification.identify import IdentificationError


def _keys(table: MeasurementTable) -> list[tuple[str, str]]:
    """(setup, point) of every point row, in order of first appearance."""
    if table.point is None:
        return []
    rows = np.flatnonzero(table.is_point)
    return list(dict.fromkeys(zip(table.setup[rows].tolist(), table.point[rows].tolist())))


def _lines(table: MeasurementTable, rows) -> str:
    shown = ", ".join(str(n) for n in table.line[rows[:5]])
    return ("line " if len(rows) == 1 else "lines ") + shown + (" ..." if len(rows) > 5 else "")


def _check_rows(table: MeasurementTable, fixture: Fixture | None, placed=()) -> None:
    """Every point of the form known to the fixture and seated at least MIN_ROWS_PER_POINT times (but for
    those in ``placed``: points the calibration placed, which validation rows only revisit)."""
    for setup, point in _keys(table):
        rows = np.flatnonzero((table.setup == setup) & (table.point == point))
        if fixture is not None and point not in fixture.points:
            raise DatasetError(f"{table.path}:{table.line[rows[0]]}: column 'point': {point!r} is not a point of the "
                               f"fixture {fixture.path} (points: {', '.join(fixture.points)}); check the id or add it "
                               "to the fixture file")
        if len(rows) < MIN_ROWS_PER_POINT and (setup, point) not in placed:
            raise DatasetError(f"{table.path}:{table.line[rows[0]]}: column 'point': point {point!r} of setup "
                               f"{setup!r} has {len(rows)} row{'s' if len(rows) != 1 else ''} ({_lines(table, rows)}); "
                               f"an unknown point needs at least {MIN_ROWS_PER_POINT}, in different orientations")


def _check_fixture_used(fixture: Fixture, tables) -> None:
    seen = {p for t in tables if t is not None and t.point is not None for p in t.point[t.is_point].tolist()}
    for i, p in enumerate(fixture.points):
        if p not in seen:
            raise FixtureError(f"{p!r} does not occur in the data's point column ("
                               f"{', '.join(sorted({t.path for t in tables if t is not None}))}); remove it or "
                               "check the ids", source=fixture.path, key=f"points[{i}]")


def _distances(keys, fixture: Fixture | None):
    """(index a, index b, mm, sd) for each fixture distance whose two points occur in the same setup."""
    if fixture is None:
        return ()
    index = {k: i for i, k in enumerate(keys)}
    out = []
    for setup in dict.fromkeys(s for s, _ in keys):
        for d in fixture.distances:
            if (setup, d.a) in index and (setup, d.b) in index:
                out.append((index[(setup, d.a)], index[(setup, d.b)], d.mm, d.sd_mm))
    return tuple(out)


def _check_setups(table: MeasurementTable, keys, fixture: Fixture | None) -> None:
    """In a calibration without measured positions, every setup's points must be tied by a known distance:
    joint angles and points alone never fix the arm's size."""
    if (~table.is_point).any():
        return  # measured positions fix the scale
    tied = {keys[a][0] for a, _, _, _ in _distances(keys, fixture)}
    for setup in dict.fromkeys(s for s, _ in keys):
        if setup in tied:
            continue
        mine = [p for s, p in keys if s == setup]
        first = int(np.flatnonzero(table.setup == setup)[0])
        what = (f"has one point ({mine[0]!r}) and no known distance" if len(mine) == 1 else
                f"has points {', '.join(map(repr, mine))} but " +
                ("no --fixture gives a distance between them" if fixture is None else
                 f"the fixture {fixture.path} gives no distance between them"))
        raise DatasetError(f"{table.path}:{table.line[first]}: column 'setup': setup {setup!r} {what}; without one "
                           "the rows only say that the arm came back to the same spot, which cannot fix its lengths: "
                           "seat the tool in a second socket of the plate (a distance in --fixture), or add measured "
                           "positions")


def _data(table: MeasurementTable, keys, fixture, target_names) -> PointData:
    index = {k: i for i, k in enumerate(keys)}
    point = np.array([index[(s, p)] if p else -1 for s, p in zip(table.setup.tolist(), table.point.tolist())]
                     if table.point is not None else np.full(len(table), -1), dtype=int)
    targets = {t: i for i, t in enumerate(target_names)}
    target = np.array([targets[table.target_names[t]] for t in table.target], dtype=int)
    return PointData(table.q_rad, target, tuple(target_names), point, tuple(keys), table.xyz_mm,
                     _distances(keys, fixture))


def run(args, model, cal: MeasurementTable, val: MeasurementTable | None, fixture: Fixture | None,
        overlap: int = 0) -> int:
    """identify on point-form rows; `overlap`: how many validation rows are calibration rows."""
    if args.loss != "linear":
        raise UsageError(f"--loss {args.loss}: the point form is fitted by least squares (its rows are seatings, "
                         "each a repeatability; leave --loss out)")
    if getattr(args, "regularize", None) is not None:
        raise UsageError(f"--regularize {args.regularize}: the point form is fitted by least squares with the prior "
                         "--prior-mm sets, not by cross-validated ridge; leave --regularize out")
    _check_rows(cal, fixture)
    if val is not None:
        _check_rows(val, fixture, placed=set(_keys(cal)))
        if (~val.is_point).any() and not (~cal.is_point).any():
            first = int(np.flatnonzero(~val.is_point)[0])
            raise DatasetError(f"{val.path}:{val.line[first]}: column 'x_mm': a measured position to validate on, but "
                               f"the calibration rows of {args.data} have none, so the instrument's frame is unknown; "
                               "validate on point rows, or calibrate with measured positions too")
    if fixture is not None:
        _check_fixture_used(fixture, (cal, val))
    keys = _keys(cal)
    if not keys:
        if fixture is None:
            raise UsageError(f"{val.path}: point rows to validate on, but the calibration rows of {args.data} have no "
                             "point; a calibration from measured positions is validated on measured positions")
        raise UsageError(f"{args.fixture}: --fixture given, but the calibration rows of {args.data} have no point "
                         "(a point column naming the socket or stylus each row sat at)")
    _check_setups(cal, keys, fixture)
    options = FixtureOptions(
        seating_sd_mm=fixture.seating_sd_mm if fixture else FixtureOptions.seating_sd_mm,
        stylus_radius_mm=fixture.stylus_radius_mm if fixture else None,
        fixed=tuple(args.fix or ()), prior_mm=args.prior_mm)
    data = _data(cal, keys, fixture, cal.target_names)
    result = identify_points(model, data, options, progress=print_progress)
    validation = None
    if val is not None:
        validation = _validate(model, result, data, val, fixture, cal.target_names, options)
    doc = fixture_json(result, data, validation, model.name)
    if "validate" in doc:
        doc["validate"]["overlap_rows"] = overlap
    misfit = distance_misfit(result, data, args.fixture or cal.path)
    if misfit is not None:
        doc["success"] = False
        doc["error"] = {"code": 1, "message": misfit}
    if args.json:
        print(json.dumps(doc))
    else:
        print(fixture_text(doc, result))
    if args.write_model and (misfit is None or args.force):
        _write_model(args, model, result, cal, validation, options)
    if misfit is not None:
        print_progress(f"error: {misfit}; " + ("the model was written all the same (--force)" if args.write_model
                                               and args.force else "no model written (--force writes it)"))
        return 1
    return 0


def _validate(model, result, data: PointData, val: MeasurementTable, fixture, target_names, options) -> dict:
    """Kinematics and target offsets as calibrated; each validation setup the calibration never saw gets its
    points placed anew (with the fixture's distances); the rest keep the calibration's points."""
    keys = _keys(val)
    cal_index = {k: i for i, k in enumerate(data.points)}
    known = {i: result.point_positions[cal_index[k]] for i, k in enumerate(keys) if k in cal_index}
    vdata = _data(val, keys, fixture, target_names)
    base = result.base if result.unknowns.with_base else None
    errors, _ = refit_points(model, result.k, result.offsets, base, vdata, known, options)
    nominal_k = result.z_nominal[: result.unknowns.n_kin]
    nominal_offsets = np.stack([result.z_nominal[result.unknowns.target(i)] for i in range(len(target_names))])
    nominal_base = result.z_nominal[result.unknowns.base] if result.unknowns.with_base else None
    known_nominal = {i: result.z_nominal[result.unknowns.point(cal_index[k])] for i, k in enumerate(keys)
                     if k in cal_index}
    before, _ = refit_points(model, nominal_k, nominal_offsets, nominal_base, vdata, known_nominal, options)
    new_setups = sorted({s for s, _ in keys} - {s for s, _ in data.points})
    return {"errors": errors, "before": before, "rows": len(val), "path": val.path,
            "setups": len({s for s, _ in keys}), "points": len(keys), "refitted_points": len(keys) - len(known),
            "new_setups": new_setups}


def _write_model(args, model, result, cal: MeasurementTable, validation, options: FixtureOptions) -> None:
    if validation is not None:
        heldout = float(validation["errors"].mean())
        how = (f"validation rows ({validation['rows']}): {validation['refitted_points']} point(s) of setups the "
               "calibration never saw placed anew, kinematics as calibrated")
    else:
        heldout, how = None, "none: no validation rows (point form: give --validate with a setup of its own)"
    calibrated = from_fit(model, cal.target_names, result.tracker_x(cal.target_names))
    # a seating's distance from its point, were the fit perfect: the seating sd in each of three axes
    noise = options.seating_sd_mm * np.sqrt(3.0)
    model_out.write_model(args.write_model, calibrated, args.robot,
                          model_out.provenance("identify", args.data, len(cal), heldout, how, result.errors_mm, noise),
                          drawn=model_out.drawn_targets(args, cal.target_names))


# A known distance the fit leaves further from its stated value than this many of its standard
# deviations is not a distance of this fixture: a fit that meets its distances leaves them within
# about one sd (the seatings pull a distance by far less than its sd when it is right).
MISFIT_SD = 5.0


def distance_misfit(result, data: PointData, path) -> str | None:
    """Why the fit does not meet its fixture's known distances (the worst, beyond MISFIT_SD of its sd:
    a wrong distance in the fixture file, or a bar of another length), or None."""
    worst = None
    for a, b, mm, sd in data.distances:
        fitted = float(np.linalg.norm(result.point_positions[a] - result.point_positions[b]))
        z = abs(fitted - mm) / sd
        if z > MISFIT_SD and (worst is None or z > worst[0]):
            worst = (z, a, b, mm, sd, fitted)
    if worst is None:
        return None
    z, a, b, mm, sd, fitted = worst
    (setup, pa), (_, pb) = data.points[a], data.points[b]
    rms = float(np.sqrt(np.mean(result.errors_mm ** 2)))
    return (f"{path}: the distance {pa}-{pb} of setup {setup} is given as {mm:g} mm (sd {sd:g}); the fit leaves it at "
            f"{fitted:.3f} mm, {z:.0f} sd away, with the seatings {rms:.3f} mm rms from their points: the data say "
            f"the distance is {'shorter' if fitted < mm else 'longer'} (is the fixture file right?)")


def fixture_fit_for_analysis(args, model, table: MeasurementTable, fixture: Fixture | None):
    """``cellcal analyze`` on point-form rows: the same checks as identify's, then the fixture calibration
    that is the analysis' geometric baseline. Returns (fit, PointData)."""
    if (~table.is_point).any():
        first = int(np.flatnonzero(~table.is_point)[0])
        raise DatasetError(f"{table.path}:{table.line[first]}: column 'x_mm': a measured position among point rows; "
                           "analyze takes point rows or measured positions, not both in one analysis: split the file")
    for flag, given in (("--validate", args.validate), ("--discriminate", getattr(args, "discriminate", None))):
        if given:
            raise UsageError(f"{flag} with point-form rows: it carries effects between tracker campaigns (or designs "
                             "tracker poses); analyze the point rows without it")
    if args.loss != "linear":
        raise UsageError(f"--loss {args.loss}: point-form rows are fitted by least squares (leave --loss out)")
    _check_rows(table, fixture)
    if fixture is not None:
        _check_fixture_used(fixture, (table,))
    keys = _keys(table)
    _check_setups(table, keys, fixture)
    options = FixtureOptions(seating_sd_mm=fixture.seating_sd_mm if fixture else FixtureOptions.seating_sd_mm,
                             stylus_radius_mm=fixture.stylus_radius_mm if fixture else None)
    data = _data(table, keys, fixture, table.target_names)
    fit = identify_points(model, data, options, progress=print_progress)
    misfit = distance_misfit(fit, data, args.fixture or table.path)
    if misfit is not None:  # the baseline fails its own fixture: what is left over is the wrong distance
        raise IdentificationError(f"{misfit}; no effect is named over a baseline that does not fit its fixture")
    return fit, data
