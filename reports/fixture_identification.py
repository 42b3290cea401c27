"""The JSON object and the text of ``cellcal identify`` on point-form data (fixtures as the instrument).

Units at this edge are the ones people read: mm and degrees. What the data cannot determine
is never printed as identified: kinematic parameters held at nominal say why ("held"), and
the frame the points are given in is listed under "conventions".
"""
from __future__ import annotations

import numpy as np

from cellcal.reports.identification import error_stats, fit_diagnostics
from cellcal.solvers.fixtures.fixture_identify import FixtureIdentification
from cellcal.solvers.fixtures.fixture_predict import WorkspaceJudgement, judge_workspace
from cellcal.solvers.fixtures.point_problem import PointData


def _human(value: float, is_angle: bool) -> float:
    return float(np.rad2deg(value)) if is_angle else float(value)


def _held(result: FixtureIdentification) -> dict[str, str]:
    reasons = {n: "not identifiable from this data (below the noise)" for n in result.unidentifiable}
    reasons.update({n: "not seen by fixture data at all (a convention)" for n in result.absorbed})
    reasons.update({h.name: "held after the fit: " + h.reason for h in result.held_implausible})
    reasons.update({n: "held on request" for n in result.fixed})
    return reasons


def fixture_json(result: FixtureIdentification, data: PointData, validation: dict | None, robot: str) -> dict:
    u = result.unknowns
    model = u.model
    is_angle = u.is_angle()
    held = _held(result)
    parameters = []
    for i, name in enumerate(model.param_names):
        parameters.append({
            "name": name, "unit": "deg" if is_angle[i] else "mm",
            "nominal": _human(model.nominal[i], is_angle[i]), "value": _human(result.z[i], is_angle[i]),
            "identified": _human(result.z[i], is_angle[i]) if result.free[i] else None,
            "std": _human(result.std[i], is_angle[i]) if result.free[i] else None,
            "estimated": bool(result.free[i]), "held": held.get(name)})
    targets = {t: {"offset_mm": result.z[u.target(i)].tolist(), "std_mm": result.std[u.target(i)].tolist()}
               for i, t in enumerate(data.target_names)}
    points = [{"setup": s, "point": p, "position_mm": result.z[u.point(i)].tolist(),
               "std_mm": result.std[u.point(i)].tolist()} for i, (s, p) in enumerate(data.points)]
    distances = [{"setup": data.points[a][0], "a": data.points[a][1], "b": data.points[b][1], "known_mm": mm,
                  "sd_mm": sd, "fitted_mm": mm + float(m)}
                 for (a, b, mm, sd), m in zip(data.distances, result.distance_misfit_mm)]
    out = {
        "form": "point",
        "robot": robot,
        "rows": int(len(data)),
        "point_rows": int(data.is_point.sum()),
        "position_rows": int((~data.is_point).sum()),
        "setups": len({s for s, _ in data.points}),
        "points": len(data.points),
        "distances": len(data.distances),
        "contact": result.options.stylus_radius_mm is not None,
        "train": error_stats(result.errors_mm),
        "before": {"train_mean_mm": float(result.errors_nominal_mm.mean())},
        "parameters": parameters,
        "unidentifiable": [n for n in model.param_names if n in held and n not in result.fixed],
        "held_implausible": [{"name": h.name, "unit": "deg" if h.is_angle else "mm", "reason": h.reason,
                              "rejected_value": _human(h.value, h.is_angle),
                              "rejected_std": _human(h.std, h.is_angle), "nominal": _human(h.nominal, h.is_angle)}
                             for h in result.held_implausible],
        "fixed": list(result.fixed),
        "conventions": list(result.conventions),
        "targets": targets,
        "fixture_points": points,
        "fixture_distances": distances,
        "instrument": (None if not u.with_base else
                       {"t_mm": result.base[:3].tolist(), "rotvec_deg": np.rad2deg(result.base[3:]).tolist()}),
        "workspace": _workspace(model, result),
        **fit_diagnostics(result),
    }
    if validation is not None:
        out["validate"] = {**error_stats(validation["errors"]), "rows": validation["rows"],
                           "setups": validation["setups"], "points": validation["points"],
                           "refitted_points": validation["refitted_points"], "new_setups": validation["new_setups"]}
        out["before"]["validate_mean_mm"] = float(np.mean(validation["before"]))
    return out


def _workspace(model, result: FixtureIdentification) -> dict:
    w = judge_workspace(model, result)
    return {"expected_error_mm": w.expected_error_mm, "correction_mm": w.correction_mm, "poses": w.poses,
            "trustworthy": w.trustworthy}


def fixture_text(doc: dict, result: FixtureIdentification) -> str:
    lines = [f"cellcal identify: {doc['robot']}, point form: {doc['rows']} rows at {doc['points']} points in "
             f"{doc['setups']} setup{'s' if doc['setups'] != 1 else ''}, {doc['distances']} known distance"
             f"{'s' if doc['distances'] != 1 else ''}" + (" (stylus contacts)" if doc["contact"] else ""), ""]
    what = "distance from the ball's surface" if doc["contact"] else "distance from the point"
    lines.append(f"{'':24s}{'before':>10s}{'after':>10s}   (mean {what}, mm)")
    lines.append(f"{'calibration data':24s}{doc['before']['train_mean_mm']:10.3f}{doc['train']['mean_mm']:10.3f}")
    if "validate" in doc:
        v = doc["validate"]
        lines.append(f"{'validation data':24s}{doc['before']['validate_mean_mm']:10.3f}{v['mean_mm']:10.3f}   "
                     f"(max {v['max_mm']:.3f}; {v['rows']} rows, {v['points']} points in {v['setups']} setups, "
                     f"{v['refitted_points']} placed anew)")
    lines.append("")
    lines.append(f"{'parameter':18s}{'nominal':>12s}{'identified':>12s}{'std':>10s}")
    for row in doc["parameters"]:
        std = (f"{row['std']:.4f}" if row["std"] is not None else
               "fixed" if row["name"] in result.fixed else
               "held*" if row["name"] in {h.name for h in result.held_implausible} else "held")
        shown = "" if row["std"] is None else f"{row['identified']:12.4f}"
        lines.append(f"{row['name'] + ' [' + row['unit'] + ']':18s}{row['nominal']:12.4f}{shown:>12s}{std:>10s}")
    for name, t in doc["targets"].items():
        lines.append(f"target {name} offset [mm]: " + ", ".join(f"{v:.4f}" for v in t["offset_mm"])
                     + " (std " + ", ".join(f"{s:.4f}" for s in t["std_mm"]) + ")")
    lines.append("")
    if doc["unidentifiable"]:
        lines.append("held: not determined by this data, reported at nominal (not identified): "
                     + ", ".join(doc["unidentifiable"]))
    for h in doc["held_implausible"]:
        lines.append(f"  held* {h['name']}: the fit gave {h['rejected_value']:.4g} +- {h['rejected_std']:.4g} "
                     f"{h['unit']}; {h['reason']}")
    for c in doc["conventions"]:
        lines.append(f"convention: {c}")
    for d in doc["fixture_distances"]:
        lines.append(f"setup {d['setup']}: {d['a']} - {d['b']} fitted {d['fitted_mm']:.4f} mm "
                     f"(known {d['known_mm']:g} +- {d['sd_mm']:g})")
    lines.append(f"residual noise {doc['noise_mm'] * 1000:.1f} um; {doc['structural_rank']} geometric directions "
                 f"seen, {doc['noise_rank']} above the noise; condition {doc['condition']:.3g}; {doc['seconds']:.2f} s")
    lines.append(WorkspaceJudgement(**{k: v for k, v in doc["workspace"].items() if k != "trustworthy"}).describe())
    lines.append(f"fit status {doc['status']}: {doc['message']}")
    return "\n".join(lines)
