"""What people and scripts read of a result: the JSON object and the text table.

Units at this edge are the ones people read: mm and degrees.
"""
from __future__ import annotations

import numpy as np

from cellcal.solvers.identification.identify import Identification
from cellcal.solvers.identification.measurement_model import Observations, predict


def error_stats(errors: np.ndarray) -> dict:
    errors = np.asarray(errors, dtype=float)
    return {"mean_mm": float(errors.mean()), "rms_mm": float(np.sqrt(np.mean(errors**2))),
            "max_mm": float(errors.max()), "n": int(len(errors))}


def _errors(result: Identification, x: np.ndarray, obs: Observations) -> np.ndarray:
    return np.linalg.norm(predict(result.layout, x, obs) - obs.xyz_mm, axis=1)


def _human(value: float, is_angle: bool) -> float:
    return float(np.rad2deg(value)) if is_angle else float(value)


def _held_reasons(result: Identification) -> dict[str, str]:
    reasons = {name: "not identifiable from this data" for name in result.unidentifiable}
    reasons.update({h.name: "held after the fit: " + h.reason for h in result.held_implausible})
    reasons.update({name: "held on request" for name in result.fixed})
    return reasons


def parameter_rows(result: Identification) -> list[dict]:
    layout = result.layout
    nominal = layout.initial()
    nominal[layout.n_kin:] = np.nan  # base and targets have no nominal
    held = _held_reasons(result)
    rows = []
    for i, (name, is_angle) in enumerate(zip(layout.names, layout.is_angle)):
        kinematic = i < layout.n_kin
        rows.append({
            "name": name,
            "unit": "deg" if is_angle else "mm",
            "nominal": _human(nominal[i], is_angle) if kinematic else None,
            "identified": _human(result.x[i], is_angle),
            "std": _human(result.std[i], is_angle) if result.free[i] else None,
            "estimated": bool(result.free[i]),
            "held": held.get(name),  # why it is at nominal, in words; None when estimated
            "uncertain": name in result.uncertain,  # estimated but beyond the trust bounds
        })
    return rows


def held_rows(result: Identification) -> list[dict]:
    """Parameters held at nominal after the fit, with the values that were rejected."""
    return [{"name": h.name, "unit": "deg" if h.is_angle else "mm", "reason": h.reason,
             "rejected_value": _human(h.value, h.is_angle), "rejected_std": _human(h.std, h.is_angle),
             "nominal": _human(h.nominal, h.is_angle), "moved_with": list(h.partners),
             "calibration_rms_rise_mm": h.rms_rise_mm}
            for h in result.held_implausible]


def group_rows(result: Identification) -> list[dict]:
    return [{"parameters": list(g.names), "max_abs_r": g.max_abs_r, "effect_mm": g.effect_mm,
             "single_effect_mm": g.single_effect_mm}
            for g in result.correlated]


def fit_diagnostics(result) -> dict:
    """How the fit went, the same keys for every identification's JSON (docs/cli.md)."""
    return {"noise_mm": result.noise_mm, "structural_rank": result.structural_rank, "noise_rank": result.noise_rank,
            "condition": result.condition, "status": result.status, "success": result.success,
            "message": result.message, "seconds": result.seconds}


def identification_json(result: Identification, obs: Observations, val: Observations | None,
                        val_x: tuple[np.ndarray, np.ndarray] | None = None) -> dict:
    """The JSON of ``cellcal identify``.

    "unidentifiable" names every geometric parameter the data cannot determine and that
    is reported at nominal: those the analysis held before the fit and those held after
    it ("held_implausible" gives each one's reason and the value that was rejected).
    """
    out = {
        "train": error_stats(_errors(result, result.x, obs)),
        "before": {"train_mean_mm": float(_errors(result, result.x_nominal, obs).mean())},
        "parameters": parameter_rows(result),
        "unidentifiable": list(result.unidentifiable) + [h.name for h in result.held_implausible],
        "held_implausible": held_rows(result),
        "uncertain": list(result.uncertain),
        "correlated_groups": group_rows(result),
        "weakly_identifiable": list(result.weakly_identifiable),
        "fixed": list(result.fixed),
        "regularize": {"lambda": result.lam,
                       "cv_curve": [{"lambda": lam, "heldout_mean_mm": e} for lam, e in result.cv_curve]},
        **fit_diagnostics(result),
    }
    if val is not None:  # val_x: the calibrated and nominal x with the validation rows' own frame and offsets
        x_after, x_before = (result.x, result.x_nominal) if val_x is None else val_x
        out["validate"] = {**error_stats(_errors(result, x_after, val)), "setup": "same" if val_x is None else "new"}
        out["before"]["validate_mean_mm"] = float(_errors(result, x_before, val).mean())
    return out


def _value(value: float, unit: str) -> str:
    return f"{value:.4g} {unit}"


def identification_text(result: Identification, obs: Observations, val: Observations | None,
                        robot: str, val_x: tuple[np.ndarray, np.ndarray] | None = None) -> str:
    doc = identification_json(result, obs, val, val_x)
    setup = ("the same setup: frame and target offsets as calibrated" if val_x is None else
             "its own frame and target offsets fitted on it")
    lines = [f"cellcal identify: {robot}, {len(obs)} calibration measurements"
             + (f", {len(val)} validation ({setup})" if val is not None else ""), ""]
    lines.append(f"{'':24s}{'before':>10s}{'after':>10s}   (mean error, mm)")
    lines.append(f"{'calibration data':24s}{doc['before']['train_mean_mm']:10.3f}{doc['train']['mean_mm']:10.3f}")
    if val is not None:
        lines.append(f"{'validation data':24s}{doc['before']['validate_mean_mm']:10.3f}"
                     f"{doc['validate']['mean_mm']:10.3f}   (max {doc['validate']['max_mm']:.3f})")
    lines.append("")
    held_after = {h.name for h in result.held_implausible}
    lines.append(f"{'parameter':18s}{'nominal':>12s}{'identified':>12s}{'std':>10s}")
    for row in doc["parameters"]:
        nominal = "" if row["nominal"] is None else f"{row['nominal']:12.4f}"
        if row["std"] is not None:
            std = f"{row['std']:.4f}" + ("?" if row["uncertain"] else "")
        else:
            std = "fixed" if row["name"] in result.fixed else "held*" if row["name"] in held_after else "held"
        lines.append(f"{row['name'] + ' [' + row['unit'] + ']':18s}{nominal:>12s}{row['identified']:12.4f}{std:>10s}")
    lines.append("")
    if result.unidentifiable:
        lines.append("held: not identifiable from this data (held at nominal): " + ", ".join(result.unidentifiable))
    if doc["held_implausible"]:
        lines.append("held*: held at nominal after the fit, because the data cannot pin them down "
                     "(a value this uncertain or this far from nominal says nothing about the robot):")
        for h in doc["held_implausible"]:
            moved = f"; it moved together with {', '.join(h['moved_with'])}" if h["moved_with"] else ""
            lines.append(f"  {h['name']}: the fit gave {_value(h['rejected_value'], h['unit'])} "
                         f"+- {_value(h['rejected_std'], h['unit'])} (nominal {_value(h['nominal'], h['unit'])}); "
                         f"{h['reason']}{moved}; holding it changes the calibration rms by "
                         f"{h['calibration_rms_rise_mm']:+.4f} mm")
    if result.uncertain:
        lines.append("?: estimated, but beyond the trust bounds with no geometric parameter left to hold "
                     "for them -- do not read them as measured: " + ", ".join(result.uncertain))
    if doc["correlated_groups"]:
        lines.append("moved together (|r| > 0.95): the data sees mostly their combination, not each one:")
        for g in doc["correlated_groups"]:
            lines.append(f"  {', '.join(g['parameters'])} (|r| up to {g['max_abs_r']:.3f}): their joint move off "
                         f"nominal changes the targets by {g['effect_mm']:.3f} mm rms; the largest single one "
                         f"alone by {g['single_effect_mm']:.3f} mm")
    weak = result.weakly_identifiable
    if weak:
        help_ = "with the prior's help" if result.lam > 0 else "without a prior (weight 0), inside the trust bounds"
        lines.append(f"below the noise on their own, estimated {help_}: " + ", ".join(weak))
    if result.fixed:
        lines.append("fixed: held at nominal on request: " + ", ".join(result.fixed))
    if result.cv_curve:
        lines.append(f"L2 prior weight chosen by cross-validation: {result.lam:.3g}")
    lines.append(f"residual noise {result.noise_mm * 1000:.1f} um per axis; condition {result.condition:.3g}; "
                 f"{result.seconds:.2f} s")
    lines.append(f"fit status {result.status}: {result.message}")
    return "\n".join(lines)
