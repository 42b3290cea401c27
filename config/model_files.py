"""Calibrated robot model files: a robot file (``docs/robot-models.md``) that carries a calibration.

The file is the robot model file it was calibrated from, with the identified values
in place of the nominal ones (``joints`` rows, or a tree's ``frames`` and movable
``mount`` transforms, in the file's own units), so any reader of the plain format
gets the calibrated geometry. Two optional top-level sections extend the format
(``docs/robot-model-extension.md``):

``calibration``
    the instrument -> base frame (``base``), the flange -> target offsets (``targets``)
    and where the numbers come from (cellcal version, date, command, the data set's
    SHA-256 and row count, the held-out error).
``effects``
    the fitted effect terms: the cause, where, each parameter's value and unit, and
    whether forward kinematics applies it (``solvers.compensation.calibrated_model``).

``load_robot`` reads such a file as a plain robot model (the calibrated geometry);
``load_calibrated`` reads everything into a :class:`CalibratedModel`.
"""
from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import yaml

from cellcal.solvers.compensation.calibrated_model import STRUCTURAL, CalibratedModel, Effect, with_structural
from cellcal.solvers.analysis.effects import CAUSES
from cellcal.config.reader import Section, read_yaml
from cellcal.config.robot_files import ANGLE_UNITS, LENGTH_UNITS, ModelError, load_robot, resolve_robot

EXTENSION_KEYS = ("calibration", "effects")
CALIBRATION_KEYS = {"written_by", "command", "date_utc", "source_model", "dataset", "heldout", "train", "base",
                    "targets", "drawn_targets", "covariance", "note"}
EFFECT_KEYS = {"cause", "where", "parameters", "units", "applied", "magnitude", "extra"}
MOUNT_PARAMS = ("x", "y", "z", "rz", "ry", "rx")


def load_calibrated(name_or_path: str | Path) -> CalibratedModel:
    """A robot file with its calibration and effects (a plain file: identity base, no effects)."""
    path = resolve_robot(name_or_path)
    model = load_robot(path)
    doc = read_yaml(path, ModelError)
    top = Section(str(path), None, doc, ModelError)
    cal = top.section("calibration").expect(CALIBRATION_KEYS)
    base = np.zeros(6)
    names, offsets = ("tcp",), np.zeros((1, 3))
    if "base" in cal:
        b = cal.section("base")
        base = np.concatenate([b.vector("xyz_mm", 3, required=True), b.vector("rotvec_rad", 3, required=True)])
    if "targets" in cal:
        t = cal.section("targets")
        if not t.mapping:
            cal.fail("targets", "expected a mapping target id -> [x, y, z] in mm")
        names = tuple(str(k) for k in t.mapping)
        offsets = np.array([t.vector(k, 3) for k in t.mapping])
    effects = tuple(_effect(row) for row in top.items_of("effects"))
    model = with_structural(model, effects)
    k = model.nominal.copy()
    for e in effects:
        if e.cause == STRUCTURAL:
            for name, value in zip(e.names, e.theta):
                k[model.index(name)] = value
    model = replace(model, nominal=k)  # the calibrated values are this model's own
    return CalibratedModel(model, k, base, names, offsets, effects)


def calibration_section(name_or_path: str | Path) -> Section:
    """The ``calibration`` section of a model file (``written_by``, ``heldout``, ``train``, ``source_model`` ...;
    empty for a plain robot file), read once for :func:`drawn_targets` and :func:`covariance` and whatever
    else a command wants of it. A ModelError for a file that is not a mapping."""
    path = resolve_robot(name_or_path)
    return Section(str(path), None, read_yaml(path, ModelError), ModelError).section("calibration")


def drawn_targets(cal: Section, target_names) -> np.ndarray | None:
    """(T, 3) mm: the measured targets as the controller knows them (``drawn_targets`` of the calibration
    section ``cal``), in the order of ``target_names``; None when the file records none. A ModelError for a
    record that does not give every target as three finite numbers."""
    if "drawn_targets" not in cal:
        return None
    drawn = cal.section("drawn_targets")
    missing = [t for t in target_names if t not in drawn.mapping]
    if missing or set(drawn.mapping) - set(target_names):
        drawn.fail(None, f"expected every calibrated target ({', '.join(target_names)}) -> [x, y, z] mm, "
                         f"got {', '.join(map(str, drawn.mapping)) or 'none'}")
    return np.array([drawn.vector(t, 3) for t in target_names])


def covariance(cal: Section, names) -> np.ndarray | None:
    """(len(names), len(names)): the calibration's covariance of what it estimated (``covariance`` of the
    calibration section ``cal``: ``unknowns`` and ``matrix``, mm and rad), placed at ``names`` (a
    calibrated model's unknowns, ``Layout.names``); 0 for what it did not estimate. None when the file
    records none; a ModelError for a record that is not a symmetric matrix of known unknowns."""
    if "covariance" not in cal:
        return None
    record = cal.section("covariance").expect({"unknowns", "matrix"}, ("unknowns", "matrix"))
    unknowns, matrix = record.raw("unknowns"), record.raw("matrix")
    index = {n: i for i, n in enumerate(names)}
    if not isinstance(unknowns, list) or any(u not in index for u in unknowns) or len(set(unknowns)) != len(unknowns):
        record.fail("unknowns", f"expected a list of distinct unknowns of this model ({', '.join(names)})")
    try:
        m = np.array(matrix, dtype=float)
    except (TypeError, ValueError):
        m = np.zeros(0)
    n = len(unknowns)
    if m.shape != (n, n) or not np.isfinite(m).all() or not np.allclose(
            m, m.T, rtol=1e-9, atol=1e-9 * np.abs(np.diag(m)).max(initial=0.0)):  # as written: symmetric to its digits
        record.fail("matrix", f"expected a symmetric {n} x {n} matrix of finite numbers (mm and rad)")
    out = np.zeros((len(names), len(names)))
    at = [index[u] for u in unknowns]
    out[np.ix_(at, at)] = m
    return out


def covariance_record(cov: np.ndarray, names) -> dict:
    """``calibration.covariance`` of a covariance over ``names`` (0 rows: not estimated, left out)."""
    keep = np.flatnonzero(np.diag(cov) > 0)
    cov = 0.5 * (cov + cov.T)  # a sandwich product is symmetric up to rounding: written exactly so
    return {"unknowns": [str(names[i]) for i in keep], "matrix": [_floats(row) for row in cov[np.ix_(keep, keep)]]}


def source_model(name_or_path: str | Path) -> str | None:
    """The robot file a calibrated model started from (its nominal model), as the file records it."""
    return calibration_section(name_or_path).mapping.get("source_model")


def _effect(row: Section) -> Effect:
    row.expect(EFFECT_KEYS, ("cause", "where", "parameters"))
    cause = row.choice("cause", tuple(CAUSES))
    where = row.raw("where")
    if not isinstance(where, dict):
        row.fail("where", f"expected a mapping such as {{joint: 2}}, got {where!r}")
    params = row.section("parameters")
    if not params.mapping:
        row.fail("parameters", "expected a mapping parameter name -> value")
    names = tuple(str(n) for n in params.mapping)
    theta = np.array([params.number(n) for n in params.mapping])
    units = row.section("units")
    unit_of = tuple(str(units.raw(n, "")) for n in names)
    applied = row.flag("applied", True)
    effect = Effect(cause, dict(where), names, theta, unit_of, dict(row.raw("extra", {}) or {}))
    if applied != effect.applied:
        row.fail("applied", f"{cause} is {'' if effect.applied else 'not '}applied by this version of cellcal")
    if cause == STRUCTURAL and not all(n.startswith("beta") and n[4:].isdigit() for n in names):
        row.fail("parameters", "a parallel_axis_tilt parameter is a Hayati beta named beta<joint>")
    return effect


# -- writing -----------------------------------------------------------------------------------------


def write_calibrated(path: str | Path, calibrated: CalibratedModel, source: str | Path, provenance: dict,
                     magnitudes: dict | None = None) -> Path:
    """Write ``calibrated`` as the robot file ``source`` with the identified values in place,
    plus the ``calibration`` and ``effects`` sections. Raises OSError when it cannot write."""
    source_path = resolve_robot(source)
    doc = read_yaml(source_path, ModelError)
    for key in EXTENSION_KEYS:
        doc.pop(key, None)
    lu, au = LENGTH_UNITS[doc["length_unit"]], ANGLE_UNITS[doc["angle_unit"]]
    values = dict(zip(calibrated.model.param_names, calibrated.k))
    if "branches" in doc:
        _tree_values(doc, values, lu, au)
    else:
        for j, row in enumerate(doc["joints"], start=1):
            for key in ("a", "d"):
                row[key] = float(values[f"{key}{j}"] / lu)
            for key in ("alpha", "theta", "beta"):
                if key in row or (key != "beta"):
                    row[key] = float(values[f"{key}{j}"] / au)
    doc["calibration"] = {
        **provenance,
        "source_model": str(source),
        "base": {"xyz_mm": _floats(calibrated.base[:3]), "rotvec_rad": _floats(calibrated.base[3:])},
        "targets": {t: _floats(o) for t, o in zip(calibrated.target_names, calibrated.offsets)},
    }
    if calibrated.effects:
        doc["effects"] = [_effect_entry(e, (magnitudes or {}).get(e.cause)) for e in calibrated.effects]
    head = (f"# {doc.get('name', 'robot')}: calibrated by {provenance.get('written_by', 'cellcal')} "
            f"on {provenance.get('date_utc', '?')}\n"
            "# geometry in place of the nominal values; calibration and effects: see docs/robot-model-extension.md\n")
    out = Path(path)
    out.write_text(head + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=120))
    return out


def _effect_entry(e: Effect, magnitude: dict | None) -> dict:
    entry = {"cause": e.cause, "where": _plain(e.where),
             "parameters": {n: float(v) for n, v in zip(e.names, e.theta)},
             "units": {n: u for n, u in zip(e.names, e.units)}, "applied": e.applied}
    if e.extra:
        entry["extra"] = _plain(e.extra)
    if magnitude:
        entry["magnitude"] = _plain(magnitude)
    return entry


def _tree_values(doc, values, lu, au) -> None:
    """Identified values into a tree's frames and movable mounts (as a 3 x 4 matrix)."""
    for branch in doc["branches"]:
        name = branch["name"]
        for j, frame in enumerate(branch.get("frames") or [], start=1):
            for key, unit in (("a", lu), ("d", lu), ("alpha", au), ("theta", au)):
                frame[key] = float(values[f"{name}.{key}{j}"] / unit)
        mount = branch.get("mount")
        if mount and not mount.get("fixed", False):
            x, y, z, rz, ry, rx = (values[f"{name}.mount.{p}"] for p in MOUNT_PARAMS)
            from scipy.spatial.transform import Rotation  # imported here: 0.17 s a process that never needs it
            rot = Rotation.from_euler("ZYX", [rz, ry, rx]).as_matrix()
            branch["mount"] = {"matrix": [[*map(float, rot[i]), float((x, y, z)[i] / lu)] for i in range(3)]}


def _floats(v) -> list[float]:
    return [float(x) for x in np.asarray(v).ravel()]


def _plain(value):
    """Numbers, texts, lists and mappings only, as YAML's safe dumper takes them."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_plain(v) for v in value]
    if isinstance(value, (np.integer, int)) and not isinstance(value, bool):
        return int(value)
    if isinstance(value, (np.floating, float)):
        return float(value) if math.isfinite(value) else None
    return value
