"""``--write-model OUT.yaml`` of ``cellcal identify`` and ``cellcal analyze``: the calibrated
model file (``config.model_files``) with where its numbers come from."""
from __future__ import annotations

import datetime
import hashlib
from importlib import metadata

import numpy as np

from cellcal.config.model_files import covariance_record, write_calibrated
from cellcal.solvers.compensation.calibrated_model import from_fit
from cellcal.solvers.compensation.tool_map import fit_covariance, held_at_nominal
from cellcal.solvers.identification.measurement_model import predict
from cellcal.cli.common import UsageError, print_progress, writable_file


def check_target(path) -> None:
    """Refuse an output path that cannot be written before any computation."""
    if path is not None:
        writable_file(path, "--write-model")


MAX_DRAWN_MM = 5000.0  # a target 5 m from the flange is beyond any tool an arm carries (as compensate's --tcp-mm)


def drawn_targets(args, target_names) -> dict[str, list[float]] | None:
    """``--drawn-target [ID] X Y Z`` (repeated) as {target id: [x, y, z] mm}: each measured target as the
    controller knows it (the TCP a program sets to use it), for every target of the data or none.
    None when not given; a UsageError for anything unusable, before any computation."""
    given = getattr(args, "drawn_target", None)
    if not given:
        return None
    if args.write_model is None:
        raise UsageError("--drawn-target: recorded in the model file; give --write-model as well")
    names = tuple(str(t) for t in target_names)
    out: dict[str, list[float]] = {}
    for values in given:
        if len(values) == 3 and len(names) == 1:
            name, xyz = names[0], values
        elif len(values) == 4:
            name, xyz = values[0], values[1:]
        else:
            raise UsageError(f"--drawn-target {' '.join(values)}: give ID X Y Z (mm)" +
                             (" or, with one target, X Y Z" if len(names) == 1 else
                              f"; the data measure {len(names)} targets ({', '.join(names)})"))
        if name not in names:
            raise UsageError(f"--drawn-target {name}: not a target of the data ({', '.join(names)})")
        if name in out:
            raise UsageError(f"--drawn-target {name}: given twice")
        try:
            point = [float(v) for v in xyz]
        except ValueError:
            raise UsageError(f"--drawn-target {' '.join(values)}: X Y Z must be numbers (mm)") from None
        if not all(abs(v) <= MAX_DRAWN_MM for v in point):  # NaN and inf fail this too
            raise UsageError(f"--drawn-target {' '.join(values)}: each of X Y Z must be a finite number of mm "
                             f"within +-{MAX_DRAWN_MM:g}")
        out[name] = point
    missing = [t for t in names if t not in out]
    if missing:
        raise UsageError(f"--drawn-target: give every measured target or none; missing: {', '.join(missing)}")
    return {t: out[t] for t in names}


def provenance(command: str, data_path, rows: int, heldout_mean_mm: float | None, heldout_how: str,
               train_mm=None, noise_mm: float | None = None) -> dict:
    """The calibration section's record: who wrote it, when, from which data, how good on unseen data,
    and (``train_mm``: each training row's error) how well it fits its own data against the noise those
    data claim (``noise_mm``: the rms error a perfect fit would leave, None when the data claim none)."""
    try:
        version = metadata.version("cellcal")
    except metadata.PackageNotFoundError:
        version = "unknown"
    digest = hashlib.sha256()
    with open(data_path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return {
        "written_by": f"cellcal {version}",
        "command": command,
        "date_utc": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "dataset": {"path": str(data_path), "sha256": digest.hexdigest(), "rows": int(rows)},
        "heldout": {"mean_mm": None if heldout_mean_mm is None else float(heldout_mean_mm), "how": heldout_how},
        **({} if train_mm is None else {"train": {
            "mean_mm": float(np.mean(train_mm)), "rms_mm": float(np.sqrt(np.mean(np.square(train_mm)))),
            "noise_mm": None if noise_mm is None else float(noise_mm)}}),
    }


def write_model(path, calibrated, source, record: dict, magnitudes=None, drawn=None, cov=None) -> None:
    """The model file, with ``drawn`` ({target: [x, y, z] mm}, ``drawn_targets``) and ``cov`` (the estimates'
    covariance over ``calibrated.layout.names``) recorded when given."""
    if drawn is not None:
        record = {**record, "drawn_targets": drawn}
    if cov is not None:
        record = {**record, "covariance": covariance_record(cov, calibrated.layout.names)}
    try:
        out = write_calibrated(path, calibrated, source, record, magnitudes)
    except OSError as exc:
        raise UsageError(f"--write-model {path}: cannot write: {exc.strerror or exc}") from None
    print_progress(f"calibrated model written to {out}")


def add_argument(parser, analyze: bool = False) -> None:
    what = ("the identified geometry, instrument frame, target offsets and the named effect(s) with "
            "their fitted parameters" if analyze else
            "the identified geometry, instrument frame and target offsets")
    parser.add_argument("--write-model", metavar="OUT.yaml",
                        help=f"write a calibrated robot model file: {what} (every --robot option reads it)")
    parser.add_argument("--drawn-target", nargs="+", action="append", metavar="VALUE",
                        help="ID X Y Z, with --write-model: a measured target as the controller knows it, the TCP (mm, "
                             "flange frame) a program sets to use it, e.g. the drawing's position of the SMR; X Y Z "
                             "alone when the data measure one target. Repeat for every target. Recorded in the model file, "
                             "it lets compensate map a program's TCPs into the calibrated model and state each "
                             "target's error bound (docs/programs.md)")


def write_identified(args, model, result, rows: int, val_obs, obs=None, val_x=None) -> None:
    """identify's result as a model file; held-out error from --validate (val_x: the calibrated x with the validation
    rows' own frame and target offsets, --new-setup: the error printed), else from the CV curve."""
    if val_obs is not None and val_x is not None:
        heldout = float(np.linalg.norm(predict(result.layout, val_x, val_obs) - val_obs.xyz_mm, axis=1).mean())
        how = f"validation rows ({len(val_obs)}), another setup: their frame and target offsets fitted on them"
    elif val_obs is not None:
        heldout, how = float(result.errors(val_obs).mean()), f"validation rows ({len(val_obs)})"
    elif result.cv_curve:
        heldout = dict(result.cv_curve)[result.lam]
        how = "grouped k-fold cross-validation, linearised at the fit"
    else:
        heldout, how = None, "none: no validation rows and no cross-validation (--regularize none)"
    calibrated = from_fit(model, result.layout.target_names, result.x)
    train = None if obs is None else result.errors(obs)
    write_model(args.write_model, calibrated, args.robot, provenance("identify", args.data, rows, heldout, how, train),
                drawn=drawn_targets(args, result.layout.target_names), cov=result.covariance)


def write_finding(args, model, obs, finding) -> None:
    """analyze's finding as a model file: geometry with the named effect (both, when a second
    effect showed), or geometry alone when the finding is none."""
    scored = finding.both if finding.both is not None else finding.extended
    calibrated = from_fit(model, obs.target_names, scored.x, scored.terms, scored.theta, obs.q)
    magnitudes = {scored.cause: scored.magnitude} if len(scored.terms) == 1 else scored.magnitude
    record = provenance("analyze", args.data, len(obs), scored.heldout_mean_mm,
                        f"grouped {args.folds}-fold cross-validation ({scored.label})")
    cov = None  # the point form's rows are its points' fitted positions: their own uncertainty is not in obs
    if getattr(args, "fixture", None) is None:
        free = np.ones(calibrated.layout.size, bool)  # estimated: what the fit moved from nominal, base and offsets
        free[: calibrated.layout.n_kin] = ~held_at_nominal(calibrated, model)
        cov = fit_covariance(calibrated.layout, calibrated.x, obs, scored.residuals, free)
    write_model(args.write_model, calibrated, args.robot, record, magnitudes, drawn_targets(args, obs.target_names),
                cov)
