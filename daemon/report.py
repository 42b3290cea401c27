"""What people and scripts read of a result: the JSON object and the text table.

Units at this edge are the ones people read: mm and degrees.
"""
from __future__ import annotations

import numpy as np

from ..solvers.identify import Identification
from ..solvers.measurement_model import Observations, predict


def error_stats(errors: np.ndarray) -> dict:
    errors = np.asarray(errors, dtype=float)
    return {"mean_mm": float(errors.mean()), "rms_mm": float(np.sqrt(np.mean(errors**2))),
            "max_mm": float(errors.max()), "n": int(len(errors))}


def _errors(result: Identification, x: np.ndarray, obs: Observations) -> np.ndarray:
    return np.linalg.norm(predict(result.layout, x, obs) - obs.xyz, axis=1)


def _human(value: float, is_angle: bool) -> float:
    return float(np.rad2deg(value)) if is_angle else float(value)


def parameter_rows(result: Identification) -> list[dict]:
    layout = result.layout
    nominal = layout.initial()
    nominal[layout.n_kin:] = np.nan  # base and targets have no nominal
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
        })
    return rows


def identification_json(result: Identification, obs: Observations, val: Observations | None) -> dict:
    out = {
        "train": error_stats(_errors(result, result.x, obs)),
        "before": {"train_mean_mm": float(_errors(result, result.x_nominal, obs).mean())},
        "parameters": parameter_rows(result),
        "unidentifiable": list(result.unidentifiable),
        "weakly_identifiable": list(result.details.get("weakly_identifiable", ())),
        "fixed": list(result.fixed),
        "regularize": {"lambda": result.lam,
                       "cv_curve": [{"lambda": lam, "heldout_mean_mm": e} for lam, e in result.cv_curve]},
        "noise_mm": result.noise_mm,
        "condition": result.condition,
        "seconds": result.seconds,
    }
    if val is not None:
        out["validate"] = error_stats(_errors(result, result.x, val))
        out["before"]["validate_mean_mm"] = float(_errors(result, result.x_nominal, val).mean())
    return out


def identification_text(result: Identification, obs: Observations, val: Observations | None,
                        robot: str) -> str:
    doc = identification_json(result, obs, val)
    lines = [f"cellcal identify: {robot}, {len(obs)} calibration measurements"
             + (f", {len(val)} validation" if val is not None else ""), ""]
    lines.append(f"{'':24s}{'before':>10s}{'after':>10s}   (mean error, mm)")
    lines.append(f"{'calibration data':24s}{doc['before']['train_mean_mm']:10.3f}{doc['train']['mean_mm']:10.3f}")
    if val is not None:
        lines.append(f"{'validation data':24s}{doc['before']['validate_mean_mm']:10.3f}"
                     f"{doc['validate']['mean_mm']:10.3f}   (max {doc['validate']['max_mm']:.3f})")
    lines.append("")
    lines.append(f"{'parameter':18s}{'nominal':>12s}{'identified':>12s}{'std':>10s}")
    for row in doc["parameters"]:
        nominal = "" if row["nominal"] is None else f"{row['nominal']:12.4f}"
        std = "fixed" if row["std"] is None else f"{row['std']:.4f}"
        lines.append(f"{row['name'] + ' [' + row['unit'] + ']':18s}{nominal:>12s}{row['identified']:12.4f}{std:>10s}")
    lines.append("")
    if result.unidentifiable:
        lines.append("not identifiable from this data (held at nominal): " + ", ".join(result.unidentifiable))
    weak = result.details.get("weakly_identifiable", ())
    if weak:
        lines.append("below the noise on their own, estimated with the prior's help: " + ", ".join(weak))
    if result.fixed:
        lines.append("held at nominal on request: " + ", ".join(result.fixed))
    if result.cv_curve:
        lines.append(f"L2 prior weight chosen by cross-validation: {result.lam:.3g}")
    lines.append(f"residual noise {result.noise_mm * 1000:.1f} um per axis; condition {result.condition:.3g}; "
                 f"{result.seconds:.2f} s")
    return "\n".join(lines)
