"""What a run's report draws of the measurements against the fitted geometry.

A routine knows its geometry; the report only knows how to draw. So a routine's result
carries a :class:`Drawing`: panels of 2-D layers (mm) in the view that shows the fit best,
each layer the measurements (dots), the fitted geometry (a line) or the cell file's drawing
(dashed, or a cross for one point). The builders here turn a routine's arrays into the
usual views: edges across each beam of a light barrier, contacts on a cylinder, seats about
a pivot, axis crossings along the tool, errors per pose.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

KINDS = ("measured", "fitted", "drawn")


@dataclass(frozen=True)
class Layer:
    label: str
    xy: np.ndarray  # (N, 2) mm (or what the panel's axes say)
    kind: str = "measured"  # measured: dots; fitted: a line; drawn: the cell file's (dashed, or a cross)
    paired: bool = False  # drawn in the colour of the layer before it (a fit beside its measurements)


@dataclass(frozen=True)
class Panel:
    title: str
    xlabel: str
    ylabel: str
    layers: tuple[Layer, ...]
    equal_axes: bool = True  # a view of space: mm the same both ways


@dataclass(frozen=True)
class Drawing:
    caption: str  # what the figure shows, for the report's figure caption
    panels: tuple[Panel, ...]


def circle(radius: float, centre=(0.0, 0.0), n: int = 181) -> np.ndarray:
    t = np.linspace(0.0, 2.0 * np.pi, n)
    return np.column_stack([centre[0] + radius * np.cos(t), centre[1] + radius * np.sin(t)])


def _view(points, u, v) -> np.ndarray:
    return np.column_stack([np.asarray(points, float) @ np.asarray(u, float), np.asarray(points, float) @ v])


def beam_crossings(offsets_mm, beam, edge, bases, channels, reach_mm, drawn_off_mm) -> Drawing:
    """A light barrier: per beam, looking along it, where the tool's core was at each edge
    (from the fitted beam line; blocked and cleared apart) against the fitted reach circle.

    ``bases`` (K, 2, 3): two unit vectors across each beam; ``drawn_off_mm`` (K, 3): the cell
    file's beam point from the fitted one."""
    panels, around = [], []
    for k, channel in enumerate(channels):
        u, v = bases[k]
        rows = np.asarray(beam) == k
        seen = _view(offsets_mm[rows], u, v)
        around.append(Layer(f"beam {channel}", np.column_stack([
            np.degrees(np.arctan2(seen[:, 1], seen[:, 0])), np.linalg.norm(seen, axis=1) - reach_mm[k]])))
        layers = [Layer(f"{name} edges", _view(offsets_mm[rows & (np.asarray(edge) == name)], u, v))
                  for name in ("blocked", "cleared")]
        layers += [Layer(f"fitted reach {reach_mm[k]:.3f} mm", circle(reach_mm[k]), "fitted"),
                   Layer("beam as the cell file has it", _view(np.asarray(drawn_off_mm[k])[None], u, v), "drawn")]
        panels.append(Panel(f"beam {channel}, looking along it", "across (mm)", "up (mm)", tuple(layers)))
    panels.append(Panel("each edge off the reach circle", "where around the beam (deg)", "residual (mm)",
                        tuple(around), equal_axes=False))
    return Drawing("Each edge: where the tool's core was when it crossed (the stamp moved back by the fitted "
                   "latency), from the fitted beam line, against the fitted reach (tool radius + half the "
                   "beam's width); how far each lies off the circle (its residual) is drawn enlarged last.",
                   tuple(panels))


def contacts_on_cylinder(points_mm, kind, kept, line_point, line_dir, tip_mm, radius_mm) -> Drawing:
    """A round tool touched on a ball: the ball's centre at each contact, seen from the tool
    (flange frame), against the fitted cylinder of the contact radius about the tool axis."""
    d = np.asarray(line_dir, float) / np.linalg.norm(line_dir)
    u = np.cross(d, [1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.cross(d, [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(d, u)
    rel = np.asarray(points_mm, float) - line_point
    tip_s = float((np.asarray(tip_mm, float) - line_point) @ d)
    kind, kept = np.asarray(kind), np.asarray(kept, bool)
    groups = [(f"{name} contacts", (kind == name) & kept) for name in ("side", "face")]
    groups.append(("left out as outliers", ~kept))
    across = [Layer(label, _view(rel[rows], u, v)) for label, rows in groups if rows.any()]
    along = [Layer(label, np.column_stack([rel[rows] @ d - tip_s, np.linalg.norm(np.cross(rel[rows], d), axis=1)]))
             for label, rows in groups if rows.any()]
    s = rel @ d - tip_s
    span = np.array([min(s.min(), 0.0), max(s.max(), 0.0)])
    along += [Layer(f"fitted cylinder, radius {radius_mm:.3f} mm", np.column_stack([span, [radius_mm] * 2]), "fitted"),
              Layer("fitted TCP", np.array([[0.0, 0.0], [0.0, radius_mm]]), "fitted")]
    return Drawing("The stylus ball's centre at each contact seen from the tool (flange frame): across the fitted "
                   "axis against the circle of the contact radius, and along it from the fitted TCP.",
                   (Panel("across the tool axis", "mm", "mm", tuple(across + [Layer(
                       "fitted cylinder", circle(radius_mm), "fitted")])),
                    Panel("along the tool axis", "along the axis from the TCP (mm)", "off the axis (mm)",
                          tuple(along), equal_axes=False)))


def seats_about_pivot(flange_mm, tip_mm, kept, reach_mm, expected_mm) -> Drawing:
    """A tip seated in a pivot: the flange at each seat about the fitted pivot (on a sphere of
    the fitted reach), and the tip centre each seat puts there (the residual), enlarged."""
    kept = np.asarray(kept, bool)
    groups = [("seats", kept), ("rejected seats", ~kept)]
    panels = []
    for name, (i, j) in (("from above", (0, 1)), ("from the side", (0, 2))):
        axes = "xyz"
        flange = [Layer(label, np.asarray(flange_mm)[rows][:, [i, j]]) for label, rows in groups if rows.any()]
        panels.append(Panel(f"flange about the pivot, {name}", f"{axes[i]} (mm)", f"{axes[j]} (mm)", tuple(
            flange + [Layer(f"fitted reach {reach_mm:.2f} mm", circle(reach_mm), "fitted")])))
    tips = [Layer(label, np.asarray(tip_mm)[rows][:, :2]) for label, rows in groups if rows.any()]
    panels.append(Panel("tip centre about the fitted pivot, from above", "x (mm)", "y (mm)", tuple(
        tips + [Layer(f"expected scatter {expected_mm:.3f} mm", circle(expected_mm), "fitted")])))
    return Drawing("Each seat about the fitted pivot (base frame): the flange on the sphere of the fitted "
                   "reach, and the tip centre the fitted tool puts at each seat (its residual).", tuple(panels))


def axis_crossings(line, height_mm, measured_mm, fitted_mm, labels) -> Drawing:
    """A tool axis from opposite touches: per line of touches, where the axis crossed it at
    each height, against the fitted axis (the slope is the tilt)."""
    line = np.asarray(line)
    layers = []
    for k in sorted(set(line.tolist())):
        rows = line == k
        order = np.argsort(np.asarray(height_mm)[rows])
        h = np.asarray(height_mm, float)[rows][order]
        layers.append(Layer(labels[k], np.column_stack([h, np.asarray(measured_mm)[rows][order]])))
        layers.append(Layer("fitted axis" if k == line.min() else "_fitted axis",
                            np.column_stack([h, np.asarray(fitted_mm)[rows][order]]), "fitted", paired=True))
    return Drawing("Where the tool axis crossed each line of opposite touches, against the height back from the "
                   "tip, with the fitted axis: the slope is the tilt, a dot off its line the residual.",
                   (Panel("axis crossings along the tool", "height back from the tip (mm)",
                          "crossing less the line's offset (mm)", tuple(layers), equal_axes=False),))


def errors_per_pose(series: dict[str, tuple[np.ndarray, np.ndarray]], expected_mm: float) -> Drawing:
    """Position error per pose, before and after the fit (``series``: label -> (pose, error))."""
    layers = [Layer(label, np.column_stack([pose, error])) for label, (pose, error) in series.items() if len(pose)]
    last = max((float(np.max(p)) for p, _ in series.values() if len(p)), default=1.0)
    layers.append(Layer(f"expected noise {expected_mm:.3f} mm", np.array([[0.0, expected_mm], [last, expected_mm]]),
                        "fitted"))
    return Drawing("Each pose's position error, with the nominal model and with the identified one; the "
                   "validation poses took no part in the fit.",
                   (Panel("error per pose", "pose (in the order measured)", "error (mm)", tuple(layers),
                          equal_axes=False),))


def meeting_points(points_mm, residuals_mm, expected_mm: float) -> Drawing:
    """Two robots' tips meeting: where each meeting was (robot a's base frame, from above and
    from the side) and how far the two fitted tips stayed apart there, per axis."""
    points, residuals = np.asarray(points_mm, float), np.asarray(residuals_mm, float)
    panels = [Panel(f"meeting points, {name}", f"{'xyz'[i]} (mm)", f"{'xyz'[j]} (mm)",
                    (Layer("meetings", points[:, [i, j]]),)) for name, (i, j) in (("from above", (0, 1)),
                                                                                  ("from the side", (0, 2)))]
    n = np.arange(1, len(points) + 1)
    layers = [Layer(f"{axis} apart", np.column_stack([n, residuals[:, k]])) for k, axis in enumerate("xyz")]
    layers += [Layer(f"+- expected {expected_mm:.3f} mm", np.array([[1, expected_mm], [len(n), expected_mm]]), "fitted"),
               Layer("_expected", np.array([[1, -expected_mm], [len(n), -expected_mm]]), "fitted", paired=True)]
    panels.append(Panel("the fitted tips apart at each meeting", "meeting", "a's tip less b's (mm)", tuple(layers),
                        equal_axes=False))
    return Drawing("Where the two needle tips met (robot a's base frame), and how far apart the fitted frame and "
                   "tips put them at each meeting (the residual, per axis).", tuple(panels))
