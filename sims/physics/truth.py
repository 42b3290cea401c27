"""What a simulated cell really has: the one hidden truth every simulated device obeys.

The cell file says what the cell is *meant* to be (the tool as drawn, where the beams,
the stylus and the pivot were installed); its ``sim_truth`` section says how far
reality is from that, or states reality outright, and a seed draws the rest. From it:

* the arm as built (its geometry off the drawing; the controller still computes with
  the drawing, so its reported TCP is where it *believes* the tool is);
* the mounted tool as it really is: its tip (the TCP a perfect calibration finds), its
  axis (runout tilt), its radius and length, as a capsule that blocks beams and touches
  things with its whole body, not just a point; in a cell with a tool table, every tool
  of it as it really is (``tools``), tool 1 drawn as the one tool of a one-tool cell is and
  every other from its own stream of the seed and its id, so mounting another tool
  (:meth:`Cell.with_tool`, or a tool change at run time: :meth:`CellTruth.with_tool`, 0 for
  none, the bare flange) changes nothing else of the truth;
* the fixtures where they really are, the sensors' real latency and jitter, and the
  arm's repeatability (each motion ends a little off, drawn afresh per motion);
* in a two-robot cell, robot b as it really is (:class:`SecondArm`): its arm, its real
  needle tip, and where its base really is in robot a's base frame (the handshake's
  answer), drawn from its own stream of the seed so robot a's truth is the same as in a
  one-robot cell.

The in-process cell (:mod:`cellcal.sims.inproc.world`) and the fake UR controller behind the network
fakes (:mod:`cellcal.sims.fake_ur`) are both built from one :class:`CellTruth`, so the same routine
run in both cells is scored against the same truth. Routines and solvers never read
it; tests and the run's report (``sim_truth`` in the JSON) do.
"""
from __future__ import annotations

import math

from dataclasses import dataclass, field, replace

import numpy as np

from cellcal.config.cells import Cell, SimTruthSpec
from cellcal.config.fixture_files import Placement, cell_fixture
from cellcal.config.reader import Section
from cellcal.config.robot_files import load_robot
from cellcal.drivers.interfaces import Edge, TriggerEvent
from cellcal.solvers.geometry import se3
from cellcal.solvers.geometry.robot_model import KinematicModel
from cellcal.sims.physics.scene import ContactPlane, ContactSphere, LightBeam


@dataclass(frozen=True)
class ToolBody:
    """The real tool: a capsule of `radius_m` whose tip is the TCP, reaching `length_m` back."""

    tcp_m: np.ndarray  # the tip, flange frame
    axis: np.ndarray  # unit, flange frame, from the flange toward the tip
    radius_m: float
    length_m: float

    def segment(self, rotation: np.ndarray, position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The capsule's core segment in the frame the flange pose is given in: from the
        centre of the tip's rounding back along the axis."""
        tip = position + rotation @ self.tcp_m
        axis = rotation @ self.axis
        front = tip - axis * self.radius_m
        return front, front - axis * max(self.length_m - self.radius_m, 0.0)

    @property
    def tcp_pose(self) -> np.ndarray:
        """The tool frame a perfect calibration finds: origin at the tip, z along the axis
        (the rotation about the axis is a convention: the smallest turn from flange z)."""
        return np.concatenate([self.tcp_m, se3.rotvec_from_z(self.axis)])


FLANGE_RADIUS_M = 0.0315  # a UR's tool flange (ISO 9409-1-50-4-M6) is 63 mm across
# no tool mounted: the flange itself, a ball of its radius just behind its face (its "tip" the
# flange centre), what a beam or a surface meets when the tool changer holds no tool
BARE_FLANGE = ToolBody(np.zeros(3), np.array([0.0, 0.0, 1.0]), FLANGE_RADIUS_M, FLANGE_RADIUS_M)
TOOL_DRAWN_KEYS = ("tool_tcp_off_drawing_mm", "tool_axis_off_drawing_deg")  # the mounted tool's, in `drawn`


def tool_id_bits(tool_id: int, inputs) -> int:
    """The robot's digital input bits a tool changer sets for `tool_id`: its binary digits on
    the input numbers `inputs`, least significant first (0: none set)."""
    return sum(1 << bit for i, bit in enumerate(inputs) if int(tool_id) >> i & 1)


def tool_changer_inputs(cell: Cell | None) -> tuple:
    """The robot inputs that carry the tool changer's id in `cell` (``mounted: {robot_inputs:
    [...]}``), least significant first; () when the cell reads its tool elsewhere."""
    source = getattr(cell, "mounted_source", None)
    return tuple(source.bits) if source is not None and source.kind == "robot_inputs" else ()


@dataclass(frozen=True)
class SecondArm:
    """Robot b of a two-robot cell as it really is."""

    arm_params: np.ndarray  # as built, in its model's parameter order
    tool: ToolBody | None
    base: np.ndarray  # 4x4: robot b's base frame -> the cell frame (robot a's base), really


@dataclass(frozen=True)
class CellTruth:
    arm_params: np.ndarray  # the arm as built, in the model's parameter order (mm, rad)
    tool: ToolBody | None  # None: a point probe at whatever TCP the controller is set to
    beams: tuple[LightBeam, ...] = ()
    stylus: ContactSphere | None = None
    pivot_m: np.ndarray | None = None
    contacts: tuple = ()  # further surfaces (ContactPlane, ContactSphere)
    repeatability_mm: float = 0.0
    trigger_latency_s: float = 0.0
    trigger_jitter_s: float = 0.0
    seed: int = 0
    drawn: dict = field(default_factory=dict)  # how far each part is from the cell file, for reports
    second: SecondArm | None = None  # robot b of a two-robot cell
    tools: dict = field(default_factory=dict)  # tool id -> ToolBody: every tool of the table as it really is
    tool_id: int = 0  # which tool of `tools` is `tool` (0: none of the table, the bare flange or no table)
    tools_drawn: dict = field(default_factory=dict)  # tool id -> its `drawn` entries (how far off its drawing)
    # the kinematic-fixture plate's sockets as really placed: (setup, point id, position m), where a
    # vertical tool's tip rests in each (the plate's drawing in [kinematic_fixture], _fixture_sockets)
    sockets: tuple = ()
    # one plate the operator moves between the placements (move_by: operator): only the sockets of the
    # placement it is at are there (plate_sockets); otherwise every placement is a plate of its own
    plate_moved: bool = False
    # a stylus plate (the fixture's stylus_radius_mm): each of `sockets` is a ball's centre, the ball this
    # radius (the fixture's contact radius less the drawn tool's tip radius; true as drawn); None: sockets
    plate_ball_radius_m: float | None = None

    def plate_sockets(self, step: int = 1) -> tuple:
        """The sockets (setup, point id, position m) there are with the plate at placement `step`
        (1, 2, ...: the cell file's order) when the operator moves one plate; all of them else."""
        if not self.plate_moved:
            return self.sockets
        setups = list(dict.fromkeys(setup for setup, _, _ in self.sockets))
        if not 1 <= step <= len(setups):
            return ()  # a placement the cell file does not have: the plate is nowhere the arm reaches
        return tuple(s for s in self.sockets if s[0] == setups[step - 1])

    def with_tool(self, tool_id: int) -> "CellTruth":
        """The same cell with tool `tool_id` of the table really on the flange (a tool change),
        0 for none: the bare flange (:data:`BARE_FLANGE`). Nothing else of the truth changes, so
        it is the truth of the cell file with that tool mounted (:meth:`Cell.with_tool`).
        Raises ValueError for an id the table does not have."""
        tool_id = int(tool_id)
        if tool_id != 0 and tool_id not in self.tools:
            have = ", ".join(map(str, self.tools)) or "none"
            raise ValueError(f"no tool {tool_id} in this cell's tool table (its tools: {have}; 0: none)")
        drawn = {k: v for k, v in self.drawn.items() if k not in TOOL_DRAWN_KEYS}
        drawn.update(self.tools_drawn.get(tool_id, {}))
        return replace(self, tool=self.tools[tool_id] if tool_id else BARE_FLANGE, tool_id=tool_id, drawn=drawn)

    def with_tool_bent(self, shift_m) -> "CellTruth":
        """The same cell with the mounted tool's real tip moved by `shift_m` (flange frame, m): the
        tool bent or knocked on the flange, its axis as it was. The tool table's entry moves with it,
        so it stays bent through tool changes. Raises ValueError with no tool mounted."""
        shift = np.asarray(shift_m, dtype=float)
        if shift.shape != (3,) or not np.all(np.isfinite(shift)):
            raise ValueError("shift_m must be 3 finite numbers (m, flange frame)")
        if self.tool is None or self.tool_id == 0:
            raise ValueError("no tool is mounted: the bare flange does not bend")
        bent = replace(self.tool, tcp_m=self.tool.tcp_m + shift)
        return replace(self, tool=bent, tools={**self.tools, self.tool_id: bent} if self.tools else self.tools)

    def for_second(self) -> "CellTruth":
        """The truth robot b's own world obeys: its arm and tool, no fixtures, the same
        repeatability (its base frame is its own, as its controller's is)."""
        b = self.second
        return CellTruth(b.arm_params, b.tool, repeatability_mm=self.repeatability_mm, seed=self.seed)

    def score_base_frame(self, base_pose) -> dict:
        """How far a found pose of robot b's base in the cell frame [x, y, z, rx, ry, rz]
        (m, rad) is from the real one: its origin's distance and the rotation between them."""
        if self.second is None:
            return {}
        pose = np.asarray(base_pose, dtype=float)
        turn = se3.rotvec_to_matrix(pose[3:]).T @ self.second.base[:3, :3]
        angle = float(np.degrees(np.linalg.norm(se3.matrix_to_rotvec(turn))))
        true = np.concatenate([self.second.base[:3, 3], se3.matrix_to_rotvec(self.second.base[:3, :3])])
        return {"base_position_error_mm": float(np.linalg.norm(pose[:3] - true[:3]) * 1e3),
                "base_rotation_error_deg": angle, "true_base_frame": true.tolist()}

    def score_tips(self, tip_a_m, tip_b_m) -> dict:
        """How far found needle tips (flange frames, m) are from the real ones."""
        out = {}
        for key, tool, found in (("a", self.tool, tip_a_m), ("b", self.second and self.second.tool, tip_b_m)):
            if tool is not None and found is not None:
                out[f"tip_{key}_error_mm"] = float(np.linalg.norm(np.asarray(found, float) - tool.tcp_m) * 1e3)
        return out

    def score_tool_frame(self, tool_frame) -> dict:
        """How far a found tool frame [x, y, z, rx, ry, rz] (m, rad) is from the real tool:
        the TCP position and the direction of its z axis (the rotation about the tool axis is
        a convention, not a measurement)."""
        if self.tool is None:
            return {}
        frame = np.asarray(tool_frame, dtype=float)
        z = se3.rotvec_to_matrix(frame[3:])[:, 2]
        angle = float(np.degrees(np.arccos(np.clip(z @ self.tool.axis, -1.0, 1.0))))
        return {"position_error_mm": float(np.linalg.norm(frame[:3] - self.tool.tcp_m) * 1e3),
                "axis_error_deg": angle, "true_tool_frame": self.tool.tcp_pose.tolist()}

    def report(self) -> dict:
        """The truth in the units people read, for a simulated run's report."""
        out = {"seed": self.seed, "repeatability_mm": self.repeatability_mm,
               "trigger_latency_ms": self.trigger_latency_s * 1e3, "trigger_jitter_ms": self.trigger_jitter_s * 1e3}
        if self.tool is not None:
            out["tool"] = {"tcp_mm": (self.tool.tcp_m * 1e3).tolist(), "axis": self.tool.axis.tolist(),
                           "radius_mm": self.tool.radius_m * 1e3}
        out.update(self.drawn)
        return out


def _random_unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def _tilted(axis: np.ndarray, angle_rad: float, rng: np.random.Generator) -> np.ndarray:
    """`axis` tilted by `angle_rad` towards a random perpendicular direction."""
    perpendicular = np.cross(axis, _random_unit(rng))
    perpendicular /= np.linalg.norm(perpendicular)
    return np.cos(angle_rad) * axis + np.sin(angle_rad) * perpendicular


def truth_of_cell(cell: Cell, model: KinematicModel) -> CellTruth:
    """The truth of a simulated cell: the file's ``sim_truth`` (defaults where absent),
    with what it does not state drawn from its seed (the same seed gives the same cell)."""
    spec = cell.sim_truth or SimTruthSpec()
    rng = np.random.default_rng(spec.seed)
    params = np.asarray(model.nominal, dtype=float).copy()
    errors = np.where(model.param_is_angle, np.deg2rad(spec.arm_angle_error_deg), spec.arm_length_error_mm)
    params += rng.uniform(-1.0, 1.0, len(params)) * errors
    drawn: dict = {}
    tools = {}
    table = cell.tools or ({cell.tool.id: cell.tool} if cell.tool is not None else {})
    if 1 in table:  # tool 1 from the main stream, as a one-tool cell's tool: the fixtures' draws follow
        spec_1 = table[1]
        tcp = spec.tool_tcp_m if spec.tool_tcp_m is not None else \
            spec_1.tcp_m + _random_unit(rng) * spec.tool_tcp_error_mm / 1e3
        axis = spec.tool_axis if spec.tool_axis is not None else \
            _tilted(spec_1.axis, np.deg2rad(spec.tool_tilt_deg), rng)
        tools[1] = ToolBody(np.asarray(tcp, float), np.asarray(axis, float) / np.linalg.norm(axis),
                            spec_1.radius_m, spec_1.length_m)
    for tool_id, drawn_tool in table.items():  # every other tool from its own stream: (seed, 3, id)
        if tool_id != 1:
            tools[tool_id] = _real_tool(drawn_tool, spec, np.random.default_rng([spec.seed, 3, tool_id]))
    tool = tools[cell.tool.id] if cell.tool is not None else None
    tools_drawn = {tool_id: {"tool_tcp_off_drawing_mm": float(np.linalg.norm(real.tcp_m - table[tool_id].tcp_m) * 1e3),
                             "tool_axis_off_drawing_deg": float(np.rad2deg(np.arccos(np.clip(
                                 real.axis @ table[tool_id].axis, -1, 1))))}
                   for tool_id, real in tools.items() if real is not None}
    if tool is not None:
        drawn.update(tools_drawn[cell.tool.id])

    def placed(point: np.ndarray) -> np.ndarray:
        return np.asarray(point, float) + _random_unit(rng) * spec.fixture_error_mm / 1e3

    beams = tuple(LightBeam(placed(b.point_m), b.direction, b.radius_m, b.channel, b.level_when_blocked)
                  for b in cell.beams)
    stylus = None
    if cell.stylus is not None:
        stylus = ContactSphere(placed(cell.stylus["centre_m"]), cell.stylus["radius_m"])
    pivot = placed(cell.pivot_m) if cell.pivot_m is not None else None
    second = _second_arm(cell, spec, drawn) if "b" in cell.robots else None
    sockets = _fixture_sockets(cell, spec)
    return CellTruth(params, tool, beams, stylus, pivot, (), spec.repeatability_mm, spec.trigger_latency_s,
                     spec.trigger_jitter_s, spec.seed, drawn, second, tools,
                     cell.tool.id if cell.tool is not None else 0, tools_drawn, sockets,
                     (cell.routines.get("kinematic_fixture") or {}).get("move_by") == "operator",
                     _plate_ball_radius_m(cell))


FIXTURE_YAW_ERROR_DEG = 0.2  # a plate set down by its drawing is turned this much (1 sigma) off it


def _fixture_sockets(cell: Cell, spec: SimTruthSpec) -> tuple:
    """The kinematic-fixture plate of the cell file's [kinematic_fixture] as really placed, from the seed's
    own stream (seed, 4), so adding it changes nothing else of the truth: one plate, its sockets (a stylus
    plate: its balls' centres, at the placement's height) off their
    drawing by the fixture's distance standard deviations (half of it per coordinate and socket), each
    placement `fixture_error_mm` (a random direction) and about 0.2 deg of yaw off where the file puts it."""
    raw = cell.routines.get("kinematic_fixture")
    if raw is None:
        return ()
    placed = cell_fixture(Section(str(cell.path), "kinematic_fixture", raw), str(cell.path))
    rng = np.random.default_rng([spec.seed, 4])
    sd_mm = min((d.sd_mm for d in placed.fixture.distances), default=0.0)
    layout = {p: xy + rng.normal(0.0, sd_mm / 2.0, 2) for p, xy in placed.layout_mm.items()}
    out = []
    for setup in placed.placements:
        real = Placement(setup.name, setup.at_m + _random_unit(rng) * spec.fixture_error_mm / 1e3,
                         setup.yaw_deg + rng.normal(0.0, FIXTURE_YAW_ERROR_DEG))
        out += [(setup.name, p, real.point_m(layout[p])) for p in placed.fixture.points]
    return tuple(out)


def _plate_ball_radius_m(cell: Cell) -> float | None:
    """The balls' radius of a stylus plate in [kinematic_fixture] (None: a socket plate, or none): the
    fixture's stylus_radius_mm is where the tip's rounding centre touches, so the ball is that less the
    tool's tip radius."""
    raw = cell.routines.get("kinematic_fixture")
    if raw is None:
        return None
    radius_mm = cell_fixture(Section(str(cell.path), "kinematic_fixture", raw), str(cell.path)).fixture.stylus_radius_mm
    if radius_mm is None:
        return None
    return max(radius_mm / 1e3 - (cell.tool.radius_m if cell.tool is not None else 0.0), 0.0)


def _real_tool(drawn_tool, spec: SimTruthSpec, rng: np.random.Generator) -> ToolBody | None:
    if drawn_tool is None:
        return None
    tcp = drawn_tool.tcp_m + _random_unit(rng) * spec.tool_tcp_error_mm / 1e3
    axis = _tilted(drawn_tool.axis, np.deg2rad(spec.tool_tilt_deg), rng)
    return ToolBody(tcp, axis, drawn_tool.radius_m, drawn_tool.length_m)


def _second_arm(cell: Cell, spec: SimTruthSpec, drawn: dict) -> SecondArm:
    """Robot b as built, its real tool, and its real base: drawn from the seed's second
    stream, so adding robot b changes nothing of robot a's truth."""
    b = cell.robots["b"]
    rng = np.random.default_rng([spec.seed, 2])
    model = load_robot(b.robot)
    params = np.asarray(model.nominal, dtype=float).copy()
    errors = np.where(model.param_is_angle, np.deg2rad(spec.arm_angle_error_deg), spec.arm_length_error_mm)
    params += rng.uniform(-1.0, 1.0, len(params)) * errors
    tool = _real_tool(b.tool, spec, rng)
    turn = se3.rotvec_to_matrix(_random_unit(rng) * np.deg2rad(spec.base_error_deg))
    base = b.base_matrix.copy()
    base[:3, :3] = turn @ base[:3, :3]
    base[:3, 3] += _random_unit(rng) * spec.base_error_mm / 1e3
    drawn["base_b_off_drawing_mm"] = float(np.linalg.norm(base[:3, 3] - b.base_pose[:3]) * 1e3)
    drawn["base_b_off_drawing_deg"] = float(spec.base_error_deg)
    if tool is not None:
        drawn["tool_b_tcp_off_drawing_mm"] = float(np.linalg.norm(tool.tcp_m - b.tool.tcp_m) * 1e3)
    return SecondArm(params, tool, base)


# -- geometry of a capsule against lines, points and planes ------------------------------------

# plain floats: the simulated cells ask these of every beam and seat each 2 ms cycle, where numpy's
# per-call overhead on 3-vectors costs more than the arithmetic
def segment_line_distance(a: np.ndarray, b: np.ndarray, point: np.ndarray, direction: np.ndarray) -> float:
    """Shortest distance between the segment a-b and the line through `point` along unit `direction`."""
    (ax, ay, az), (bx, by, bz), (px, py, pz), (dx, dy, dz) = a.tolist(), b.tolist(), point.tolist(), direction.tolist()
    ax, ay, az, bx, by, bz = ax - px, ay - py, az - pz, bx - px, by - py, bz - pz
    ka, kb = ax * dx + ay * dy + az * dz, bx * dx + by * dy + bz * dz
    ux, uy, uz = ax - ka * dx, ay - ka * dy, az - ka * dz
    vx, vy, vz = bx - kb * dx - ux, by - kb * dy - uy, bz - kb * dz - uz
    vv = vx * vx + vy * vy + vz * vz
    t = 0.0 if vv < 1e-30 else min(max(-(ux * vx + uy * vy + uz * vz) / vv, 0.0), 1.0)
    return math.sqrt((ux + t * vx) ** 2 + (uy + t * vy) ** 2 + (uz + t * vz) ** 2)


def segment_point_distance(a: np.ndarray, b: np.ndarray, point: np.ndarray) -> float:
    (ax, ay, az), (bx, by, bz), (px, py, pz) = a.tolist(), b.tolist(), point.tolist()
    ux, uy, uz = bx - ax, by - ay, bz - az
    ll = ux * ux + uy * uy + uz * uz
    t = 0.0 if ll < 1e-30 else min(max(((px - ax) * ux + (py - ay) * uy + (pz - az) * uz) / ll, 0.0), 1.0)
    return math.sqrt((ax + t * ux - px) ** 2 + (ay + t * uy - py) ** 2 + (az + t * uz - pz) ** 2)


def beam_blocked(beam: LightBeam, segment, radius_m: float) -> bool:
    d = beam.direction / np.linalg.norm(beam.direction)
    return segment_line_distance(segment[0], segment[1], beam.point_m, d) < beam.radius_m + radius_m


def touching(surface, segment, radius_m: float) -> bool:
    """Whether the capsule (segment, radius) touches or pierces a contact surface."""
    if isinstance(surface, ContactSphere):
        return segment_point_distance(segment[0], segment[1], surface.centre_m) <= surface.radius_m + radius_m
    if isinstance(surface, ContactPlane):
        return min(surface.distance_m(segment[0]), surface.distance_m(segment[1])) <= radius_m
    return surface.distance_m(segment[0]) <= radius_m


def switching_fraction(blocked_at, steps: int = 24) -> float:
    """Fraction s in [0, 1] of a step at which `blocked_at(s)` first differs from its value
    at 0 (bisection; the body moves on a straight line within one 2 ms cycle)."""
    start, lo, hi = blocked_at(0.0), 0.0, 1.0
    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        if blocked_at(mid) == start:
            lo = mid
        else:
            hi = mid
    return hi


# -- the physics both simulated cells run (SimWorld in process, the fake UR controller) ---------

def repeat_offset_m(truth: CellTruth, rng: np.random.Generator) -> np.ndarray:
    """How far a new motion really ends from where the controller puts it: the arm's
    repeatability, drawn afresh for each motion (base frame, m)."""
    sigma = truth.repeatability_mm / 1e3 / np.sqrt(3.0)
    return rng.normal(0.0, sigma, 3) if sigma > 0 else np.zeros(3)


def real_tool_body(truth: CellTruth, physics, controller, q, tcp_offset, offset_m) -> tuple[np.ndarray, np.ndarray]:
    """The real tool's core segment (base frame, m) at joints q: the real tool on the arm as
    built (`physics`, an ArmKinematics of ``truth.arm_params``), off by the motion's
    repeatability `offset_m`. Without a tool in the truth, a point at the controller's TCP
    (`controller`: its kinematics; `tcp_offset`: its tool frame)."""
    if truth.tool is None:
        p = controller.tcp_frame(q, tcp_offset)[1] + offset_m
        return p, p
    rotation, position = physics.flange(q)
    front, back = truth.tool.segment(rotation, position)
    return front + offset_m, back + offset_m


def real_tool_tip(truth: CellTruth, physics, q, body) -> np.ndarray:
    """Where the real tool tip is, given its body at joints q (what a tracker target at the tip measures)."""
    front, back = body
    if truth.tool is None:
        return front.copy()
    axis = front - back
    n = np.linalg.norm(axis)
    direction = axis / n if n > 0 else physics.flange(q)[0] @ truth.tool.axis
    return front + direction * truth.tool.radius_m


def beam_edges(truth: CellTruth, beams, blocked: dict, body_old, body_new, t_old_s: float, cycle_s: float,
               rng: np.random.Generator) -> list[TriggerEvent]:
    """The sensor edges of one controller cycle in which the real tool moved from `body_old`
    to `body_new` (segments). A beam switches where the tool's straight step crosses it
    (bisection), not at the cycle that first shows the new level; its time adds the
    sensor's latency and a jitter drawn uniformly from [-jitter, +jitter]. `blocked`
    (id(beam) -> bool, the beams' current state) is updated."""
    radius = 0.0 if truth.tool is None else truth.tool.radius_m
    jitter = truth.trigger_jitter_s
    edges = []
    for beam in beams:
        now = beam_blocked(beam, body_new, radius)
        if now == blocked[id(beam)]:
            continue
        blocked[id(beam)] = now

        def blocked_at(s, beam=beam):
            mixed = (body_old[0] + s * (body_new[0] - body_old[0]), body_old[1] + s * (body_new[1] - body_old[1]))
            return beam_blocked(beam, mixed, radius)

        t_edge = t_old_s + switching_fraction(blocked_at) * cycle_s
        t_edge += truth.trigger_latency_s + (rng.uniform(-jitter, jitter) if jitter > 0 else 0.0)
        edges.append(TriggerEvent(t_edge, beam.channel, Edge.BLOCKED if now else Edge.CLEARED, True))
    return edges


CUP_RIM_RADIUS_M = 0.008  # robot a's centring cup: a tip whose axis line passes within this is guided in
CUP_FACE_RADIUS_M = 0.015  # ... and one that lands within this, beside it, stays there


def meeting_touch(tip_m, partner_tip_m, partner_axis) -> str | None:
    """Whether a tip at `tip_m` has reached the other robot's tip (the plane through it
    across its unit axis): 'seat' within its centring cup's rim, 'face' beside it on the
    cup's face, None when not there."""
    d = np.asarray(tip_m, dtype=float) - partner_tip_m
    depth = float(d @ partner_axis)
    lateral = float(np.linalg.norm(d - depth * partner_axis))
    if depth > 0.0 or lateral > CUP_FACE_RADIUS_M:
        return None
    return "seat" if lateral <= CUP_RIM_RADIUS_M else "face"


def tool_axis_m(body) -> np.ndarray:
    """The unit axis (toward the tip) of a tool body (front, back)."""
    axis = body[0] - body[1]
    return axis / np.linalg.norm(axis)


def meeting_rest_q(truth: CellTruth, physics, q, meet_m, offset_m) -> np.ndarray:
    """The joints at which the real tool, its orientation held as at joints q, rests with its
    real tip at `meet_m` (where the other robot's tip is), the arm off by `offset_m`.
    Raises MotionFault when the arm cannot get there."""
    rotation, position = physics.flange(q)
    tip = position + rotation @ truth.tool.tcp_m
    return physics.ik(rotation, position + np.asarray(meet_m) - offset_m - tip, q, np.zeros(6))


def pivot_rest_q(truth: CellTruth, physics, q, seat_m, offset_m) -> np.ndarray:
    """The joints at which the real tool, its orientation held as at joints q, rests with the
    centre of its tip's rounding at `seat_m` (a socket's seat), the arm off by `offset_m`
    (that rest's repeatability draw). Raises MotionFault when the arm cannot get there."""
    rotation, position = physics.flange(q)
    centre = truth.tool.segment(rotation, position)[0]
    return physics.ik(rotation, position + np.asarray(seat_m) - offset_m - centre, q, np.zeros(6))
