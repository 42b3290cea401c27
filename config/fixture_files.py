"""The fixture file of a calibration from the cell's own fixtures (``cellcal identify --fixture``).

What is known about a fixture whose points the tool seats in (sockets) or touches (a
stylus ball), as docs/measurements.md ("Point form") shows it::

    points: [hole_0, hole_1]               # the fixture's point ids, as the data's point column has them
    distances_mm:                           # known distances, each with its standard deviation (mm)
      - [hole_0, hole_1, 50.0, 0.1]         # point a, point b, distance, standard deviation
    seating_sd_mm: 0.03                     # optional: how well the tool returns to a point (default 0.05)
    stylus_radius_mm: 10.0                  # optional: the points are balls the tool tip touches (ball + tip radius)

Distances hold within each setup (one placement of the fixture). With
``stylus_radius_mm`` every point is the centre of a ball and each row a contact: the
target lies that far from the centre, not at it. The radius is the distance the target
keeps from the ball's centre when touching: the ball's radius for a point target, the
ball's radius plus the tip's rounding radius when the target is the rounding's centre (as
the kinematic-fixture routine's ``tip``). Every problem is one
:class:`~cellcal.config.reader.ConfigError` naming the file and the key.
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cellcal.config.reader import ConfigError, Section, read_yaml

DEFAULT_SEATING_SD_MM = 0.05  # a ball seated in a conical socket by a compliant search returns to a few 0.01 mm
MAX_DISTANCE_MM = 5000.0  # a fixture no arm reaches across is no fixture
CONTRADICTION_SIGMAS = 3.0  # distances that miss a triangle by more than this many standard deviations contradict


class FixtureError(ConfigError):
    """A fixture file that cannot be used; the message names the file and the key."""


@dataclass(frozen=True)
class Distance:
    a: str
    b: str
    mm: float
    sd_mm: float
    key: str  # where it is in the file, e.g. distances_mm[0]


@dataclass(frozen=True)
class Fixture:
    path: str
    points: tuple[str, ...]
    distances: tuple[Distance, ...]
    seating_sd_mm: float = DEFAULT_SEATING_SD_MM
    stylus_radius_mm: float | None = None  # None: sockets (the target sits at the point)


def read_fixture(path: str | Path) -> Fixture:
    source = str(path)
    return fixture_of(Section(source, None, read_yaml(path, FixtureError), FixtureError), source)


def fixture_of(top: Section, source: str) -> Fixture:
    """The fixture a mapping describes (a fixture file's top, or a cell file's inline ``fixture:``)."""
    top.expect(("points", "distances_mm", "seating_sd_mm", "stylus_radius_mm"), required=("points",))
    raw_points = top.sequence("points", nonempty=True)
    points: list[str] = []
    for i, p in enumerate(raw_points):
        if not isinstance(p, str) or not p.strip() or p != p.strip() or "," in p:
            top.fail(f"points[{i}]", f"{p!r} is not a point id (a non-empty text without commas or surrounding "
                                     "blanks, as in the data's point column)")
        if p in points:
            top.fail(f"points[{i}]", f"{p!r} is listed twice (also points[{points.index(p)}])")
        points.append(p)
    distances: list[Distance] = []
    for i, row in enumerate(top.sequence("distances_mm", [])):
        key = f"distances_mm[{i}]"
        if not isinstance(row, list) or len(row) != 4:
            top.fail(key, f"expected [point a, point b, distance mm, standard deviation mm], got {row!r}")
        a, b, d, sd = row
        for p in (a, b):
            if p not in points:
                top.fail(key, f"{p!r} is not one of points ({', '.join(points)})")
        if a == b:
            top.fail(key, f"a distance from {a!r} to itself")
        for value, what, high in ((d, "distance", MAX_DISTANCE_MM), (sd, "standard deviation", d)):
            if not (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)):
                top.fail(key, f"the {what} {value!r} is not a number (mm)")
            if not 0 < value <= high:
                top.fail(key, f"the {what} {value!r} mm is out of range (must be above 0 and at most {high:g} mm)")
        for other in distances:
            if {other.a, other.b} == {a, b}:
                agree = abs(other.mm - d) <= CONTRADICTION_SIGMAS * math.hypot(other.sd_mm, sd)
                top.fail(key, f"{a} - {b} again ({other.key} gives {other.mm:g} mm): "
                              + ("give each pair once" if agree else "the two distances contradict each other"))
        distances.append(Distance(a, b, float(d), float(sd), key))
    _check_triangles(top, distances)
    seating = top.number("seating_sd_mm", DEFAULT_SEATING_SD_MM, above=0.0, high=5.0)
    radius = top.number("stylus_radius_mm", None, above=0.0, high=100.0) if "stylus_radius_mm" in top else None
    top.done()
    return Fixture(source, tuple(points), tuple(distances), seating, radius)


def _check_triangles(top: Section, distances: list[Distance]) -> None:
    """Refuse three distances no three points can have (one longer than the other two together,
    beyond their standard deviations)."""
    by_pair = {frozenset((d.a, d.b)): d for d in distances}
    names = sorted({p for d in distances for p in (d.a, d.b)})
    for trio in itertools.combinations(names, 3):
        sides = [by_pair.get(frozenset(pair)) for pair in itertools.combinations(trio, 2)]
        if any(s is None for s in sides):
            continue
        longest = max(sides, key=lambda s: s.mm)
        rest = [s for s in sides if s is not longest]
        slack = CONTRADICTION_SIGMAS * math.sqrt(sum(s.sd_mm ** 2 for s in sides))
        if longest.mm > rest[0].mm + rest[1].mm + slack:
            top.fail(longest.key, f"{longest.a} - {longest.b} {longest.mm:g} mm contradicts {rest[0].key} "
                                  f"({rest[0].mm:g} mm) and {rest[1].key} ({rest[1].mm:g} mm): no three points are "
                                  "that far apart; one of the three distances is wrong")


# -- a fixture placed in a cell (the kinematic-fixture routine's section; the simulated cell's truth) --

MAX_PLACEMENTS = 20


@dataclass(frozen=True)
class Placement:
    """One placement (setup) of the fixture as drawn: the plate lies flat (its z up), its origin at
    ``at_m`` in the robot's base frame, turned ``yaw_deg`` about the vertical."""

    name: str
    at_m: np.ndarray
    yaw_deg: float

    def point_m(self, layout_mm) -> np.ndarray:
        """Where a point at `layout_mm` ([x, y] on the plate, mm) is, base frame, m."""
        c, s = math.cos(math.radians(self.yaw_deg)), math.sin(math.radians(self.yaw_deg))
        x, y = np.asarray(layout_mm, dtype=float) / 1e3
        return self.at_m + np.array([c * x - s * y, s * x + c * y, 0.0])


@dataclass(frozen=True)
class CellFixture:
    fixture: Fixture
    layout_mm: dict  # point id -> [x, y] on the plate as drawn, mm
    placements: tuple[Placement, ...]


def cell_fixture(section: Section, cell_path: str | None) -> CellFixture:
    """The keys ``fixture``, ``layout_mm`` and ``placements`` of a cell file's routine section (the
    caller reads the rest and calls ``done``). ``fixture`` is a fixture file (relative to the cell
    file) or the same mapping inline; ``layout_mm`` where each of its points is on the plate as
    drawn ({id: [x, y]} mm, the plate's z up); ``placements`` the setups: [{name, at_m, yaw_deg}]."""
    raw = section.raw("fixture", required=True)
    if isinstance(raw, str):
        path = Path(raw) if Path(raw).is_absolute() or cell_path is None else Path(cell_path).parent / raw
        if not path.is_file():
            section.fail("fixture", f"no fixture file {str(path)!r} (a path relative to the cell file, or the "
                                    "fixture inline: points, distances_mm, seating_sd_mm)")
        fixture = read_fixture(path)
    elif isinstance(raw, dict):
        inline = Section(section.source, section.child_name("fixture"), raw, section.error)
        fixture = fixture_of(inline, f"{section.source} [{section.child_name('fixture')}]")
    else:
        section.fail("fixture", f"expected a fixture file's path or the fixture inline, got {raw!r}")
    layout_section = section.section("layout_mm", required=True)
    layout = {}
    for p in fixture.points:
        layout[p] = layout_section.vector(p, 2, required=True)
    layout_section.done()
    for d in fixture.distances:
        drawn = float(np.linalg.norm(layout[d.a] - layout[d.b]))
        if abs(drawn - d.mm) > CONTRADICTION_SIGMAS * d.sd_mm + 1e-9:
            layout_section.fail(d.a, f"{d.a} - {d.b} are {drawn:g} mm apart here, the fixture says "
                                     f"{d.mm:g} +- {d.sd_mm:g} mm ({d.key}): the drawing and the fixture disagree")
    if not fixture.distances:
        section.fail("fixture", "no distances_mm: without a known distance fixture data cannot fix the arm's "
                                "lengths (give at least two sockets and the distance between them)")
    placements = []
    rows = section.items_of("placements", required=True, nonempty=True)
    if len(rows) > MAX_PLACEMENTS:
        section.fail("placements", f"{len(rows)} placements; at most {MAX_PLACEMENTS}")
    for i, row in enumerate(rows):
        name = row.text("name", f"p{i + 1}")
        if not name or "," in name or name != name.strip():
            row.fail("name", f"{name!r} is not a setup id (a non-empty text without commas or surrounding blanks)")
        if name in (p.name for p in placements):
            row.fail("name", f"{name!r} names two placements")
        placements.append(Placement(name, row.vector("at_m", 3, required=True),
                                    row.number("yaw_deg", 0.0, low=-360.0, high=360.0)))
        row.done()
    return CellFixture(fixture, layout, tuple(placements))
