"""Cell files: which robot, which drivers with which options, the beam, the safety box.

A cell file is the one place that says what hardware a cell has. It is checked
completely when read (:mod:`.reader`): the first problem stops the load with one
message naming the file, the section and the key (an unknown key, a wrong type, a
value out of range), because a typo in a safety limit must not be silently ignored.

Sections (all lengths in metres, base frame unless said otherwise)::

    cell:       name, robot (model file or shipped name), home_q_rad
    drivers:    robot, trigger, tracker, panel: {driver: NAME, ...options}
    robots:     a cell of two robots instead of ``cell.robot``: ``{a: ROBOT, b: ROBOT}``, each
                ROBOT {robot, home_q_rad, driver: {driver: NAME, ...options}, tool: [tool] form,
                base_m, base_rotvec_deg (its base in the cell frame as installed; a's base
                *is* the cell frame)}. Robot a is the cell's robot for every one-robot routine.
    workspace:  min_m, max_m (the TCP's box)
    limits:     tcp_speed_m_s, tcp_accel_m_s2, joint_speed_rad_s, joint_accel_rad_s2,
                contact_travel_m (the longest a contact search may move), tool_clearance_m
                (two robots: how close their tools may come anywhere but a planned meeting)
    tool:       the mounted tool as drawn: tcp_m (flange frame), axis (flange frame, from
                the flange toward the tip), radius_m, length_m, and bands (optional: a check's
                tolerance bands, inner_mm/inner_deg (0.1/0.1) and outer_mm/outer_deg (1/1), the
                outer at most the plausibility gate's 10 mm / 5 deg; drift_mm/drift_deg, off
                unless given: a check's drift alarm, the change since the last full calibration).
                A file with ``tool`` has a table of one tool: id 1, name "tool".
    tools:      several tools instead of ``tool`` (a tool changer, a spare torch): a list of
                {id (1..255, unique), name, tcp_m, axis, radius_m, length_m, bands (as in
                ``tool``), sections (optional: routine sections that differ for this tool,
                ``{tcp_laser: {heights_mm: [...]}}``, merged key by key over the file's own
                section of that routine when the tool is mounted), frame_block (optional: its
                block of the robot's stored tool frames, 0..254, each tool its own; default its
                place in the table, 0-based: :func:`tool_blocks`)}. ``tool`` and ``tools``
                together are refused; a two-robot cell has one tool per robot, no table.
    mounted:    with ``tools``: which tool is on the flange: a tool id (fixed; default the
                table's first), ``panel`` (the panel's mounted-tool register, written by the PLC
                or the tool changer, read at each start) or ``{robot_inputs: [bit, ...]}`` (the
                tool changer's id on the robot's digital inputs, least significant bit first;
                read at each start). ``Cell.tool`` is then the table's first until the service
                reads the source (:class:`MountedSource`). :meth:`Cell.with_tool` mounts another.
    beams:      the light barrier's beams as installed: a list of
                {point_m, direction, radius_m (half the beam width), channel, level_when_blocked}
    stylus:     a fixed stylus tip: centre_m, radius_m
    pivot:      a fixed point the tool tip is seated at: point_m
    status_page: the daemon's read-only status page and JSON API: enabled (true), host
                (127.0.0.1: loopback only), port (8037), max_connections (8), rate_per_s (20,
                requests per second per client)
    plant:      what the service publishes to the plant (off when absent; docs/plant.md):
                mqtt {host, port (1883), topic, client_id (the cell's name), username,
                password_file, tls {ca, cert, key}, keepalive_s (30), outbox_limit (10000)} and
                opcua {endpoint (opc.tcp://HOST:PORT/PATH), security (none or
                Basic256Sha256_SignAndEncrypt), certificate, private_key}. File paths are taken
                from the cell file's folder; every file must be there and readable, a password
                file readable by its owner alone; a password written in the cell file is refused
    sim_truth:  what a simulated cell really has (see :class:`SimTruthSpec`); real cells
                have none. Its tool_tcp_m / tool_axis state tool 1's real frame; every other
                tool of a table is drawn, from the seed and its id
    ROUTINE:    one section per routine (``tcp_laser``, ``tcp_stylus``, ...), read by the
                routine itself (``cellcal.routines``), kept here as written. Which sections
                are routines' is the routines' to say: the caller passes their names to
                :func:`read_cell` (``cellcal.daemon.cells.load_cell`` asks the routine registry)
"""
from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np

from cellcal.config.cells import (CELL_SECTIONS, DEVICE_KINDS, PLAUSIBLE_DEG, PLAUSIBLE_MM, TOOL_IDS, Bands,
                                  BeamSpec, Cell, CellFileError, DriverSpec, MountedSource, MqttSpec, OpcuaSpec,
                                  PlantSpec, RobotSpec, SimTruthSpec, StatusPageSpec, ToolSpec, merged_sections,
                                  tool_blocks)
from cellcal.config.reader import Section, read_yaml, resolve, shipped
from cellcal.config.robot_files import ModelError, load_robot

ROBOT_INPUT_BITS = 18  # a UR's digital inputs: 0-7 standard, 8-15 configurable, 16-17 on the tool flange
_REQUIRED = ("cell", "workspace", "limits")
ROBOT_NAMES = ("a", "b")  # the robots of a two-robot cell; a's base is the cell frame


def shipped_cells() -> dict[str, Path]:
    """Cell files that ship with cellcal, by stem (``sim``, ``sim-net``)."""
    return shipped("cells")


def resolve_cell(name_or_path: str | Path) -> Path:
    """A path as given, or the name of a shipped cell (``sim``, ``sim-net``)."""
    return resolve(name_or_path, "cells", "cell", CellFileError)


def _read_status_page(top: Section) -> StatusPageSpec:
    page = top.section("status_page")
    default = StatusPageSpec()
    spec = StatusPageSpec(enabled=page.flag("enabled", default.enabled),
                          host=page.text("host", default.host),
                          port=page.integer("port", default.port, low=1, high=65535),
                          max_connections=page.integer("max_connections", default.max_connections, low=1, high=256),
                          rate_per_s=page.number("rate_per_s", default.rate_per_s, above=0.0, high=10000.0))
    page.done()
    return spec


WILDCARD_HOSTS = ("0.0.0.0", "::", "")
OPCUA_SECURITY = ("none", "Basic256Sha256_SignAndEncrypt")
_TOPIC_BAD = ("+", "#", "\0")  # MQTT wildcards and NUL: a topic to publish under holds none


def _plant_file(s: Section, key: str, cell_path: Path, *, private: bool = False) -> str | None:
    """An absolute path from a file name in ``plant:`` (relative: to the cell file's folder), or None when
    the key is absent; the file must be there and readable (private: by its owner alone)."""
    if key not in s:
        return None
    path = Path(s.text(key, required=True))
    path = path if path.is_absolute() else cell_path.parent / path
    if not path.is_file():
        s.fail(key, f"{path}: no such file")
    try:
        with open(path, "rb"):
            pass
    except OSError as exc:
        s.fail(key, f"{path}: cannot be read ({exc.strerror or exc})")
    if private and path.stat().st_mode & 0o077:
        s.fail(key, f"{path}: readable by others than its owner (mode {path.stat().st_mode & 0o777:o}); a secret "
                    f"goes in a file only the service user can read: chmod 600 {path}")
    return str(path.resolve())


def _read_plant(top: Section, cell_name: str, cell_path: Path) -> PlantSpec:
    """``plant:``: the MQTT broker and the OPC UA server the service publishes to (each off when absent)."""
    plant = top.section("plant")
    plant.expect(("mqtt", "opcua"))
    mqtt = opcua = None
    if "mqtt" in plant:
        s = plant.section("mqtt")
        if "password" in s:
            s.fail("password", "a password is not written in the cell file: put it in a file only the service user "
                               "can read (chmod 600) and give its path as password_file")
        s.expect(("host", "port", "topic", "client_id", "username", "password_file", "tls", "keepalive_s",
                  "outbox_limit"), required=("host", "topic"))
        topic = s.text("topic", required=True).strip()
        if not topic or topic.startswith("/") or topic.endswith("/") or len(topic) > 200 or any(
                c in topic for c in _TOPIC_BAD):
            s.fail("topic", f"{topic!r} is no topic to publish under: levels separated by '/', no leading or "
                            "trailing '/', no wildcard ('+', '#'), at most 200 characters")
        client_id = s.text("client_id", cell_name).strip()
        if not client_id or len(client_id) > 64:
            s.fail("client_id", "1 to 64 characters")
        username = s.text("username") if "username" in s else None
        password_file = _plant_file(s, "password_file", cell_path, private=True)
        if password_file is not None and username is None:
            s.fail("password_file", "a password needs a username: give username as well")
        tls = {"ca": None, "cert": None, "key": None}
        if "tls" in s:
            t = s.section("tls")
            t.expect(("ca", "cert", "key"))
            tls = {key: _plant_file(t, key, cell_path, private=key == "key") for key in tls}
            if (tls["cert"] is None) != (tls["key"] is None):
                t.fail("cert" if tls["cert"] is None else "key", "a client certificate needs its key, and the key "
                                                                  "its certificate: give cert and key together")
            t.done()
        mqtt = MqttSpec(host=s.text("host", required=True), topic=topic, client_id=client_id,
                        port=s.integer("port", 1883, low=1, high=65535), username=username,
                        password_file=password_file, tls_ca=tls["ca"], tls_cert=tls["cert"], tls_key=tls["key"],
                        keepalive_s=s.integer("keepalive_s", 30, low=5, high=3600),
                        outbox_limit=s.integer("outbox_limit", 10000, low=1, high=1000000))
        s.done()
    if "opcua" in plant:
        s = plant.section("opcua")
        s.expect(("endpoint", "security", "certificate", "private_key"), required=("endpoint",))
        endpoint = s.text("endpoint", required=True)
        rest = endpoint[len("opc.tcp://"):] if endpoint.startswith("opc.tcp://") else None
        host, _, port = (rest or "").split("/", 1)[0].rpartition(":")
        if rest is None or not host or not port.isdigit() or not 1 <= int(port) <= 65535:
            s.fail("endpoint", f"{endpoint!r}: expected opc.tcp://HOST:PORT/PATH")
        security = s.choice("security", OPCUA_SECURITY, "none")
        certificate = _plant_file(s, "certificate", cell_path)
        private_key = _plant_file(s, "private_key", cell_path, private=True)
        if security != "none" and (certificate is None or private_key is None):
            s.fail("certificate" if certificate is None else "private_key",
                   f"security {security} needs the server's certificate and private_key")
        opcua = OpcuaSpec(endpoint=endpoint, security=security, certificate=certificate, private_key=private_key)
        s.done()
    return PlantSpec(mqtt=mqtt, opcua=opcua)


def _check_status_port(top: Section, page: StatusPageSpec, drivers: dict) -> None:
    """The status page cannot listen where a device of the cell is served: the same port on the
    same address (or on every address, while the device is on this machine's loopback)."""
    if not page.enabled:
        return
    for role, spec in drivers.items():
        host, port = spec.options.get("host"), spec.options.get("port")
        if not isinstance(host, str) or isinstance(port, bool) or port != page.port:
            continue
        if host == page.host or (page.host in WILDCARD_HOSTS and (host.startswith("127.") or host == "localhost")):
            top.section("status_page").fail("port", f"{page.port} on {page.host} is where drivers.{role} "
                                                    f"({spec.name}) is served ({host}:{port}): give the status "
                                                    "page another port")


def _unit(section: Section, key: str, default=None, *, required=False) -> np.ndarray:
    v = section.vector(key, 3, default, required=required, nonzero=True)
    return v / np.linalg.norm(v)


def _read_tool(s: Section) -> ToolSpec:
    tool = ToolSpec(s.vector("tcp_m", 3, required=True), _unit(s, "axis", [0.0, 0.0, 1.0]),
                    s.number("radius_m", 0.003, above=0.0, high=0.1),
                    s.number("length_m", 0.1, above=0.0, high=2.0),
                    _read_bands(s.section("bands")) if "bands" in s else Bands())
    s.done()
    return tool


def _read_tools(top: Section, routine_sections: tuple | None) -> dict[int, ToolSpec]:
    """[tools]: the tool table, each row a [tool] with its id, name and routine sections."""
    tools: dict[int, ToolSpec] = {}
    rows: dict[int, Section] = {}
    for row in top.items_of("tools", nonempty=True):
        tool_id = row.integer("id", required=True, low=TOOL_IDS[0], high=TOOL_IDS[1])
        if tool_id in tools:
            row.fail("id", f"tool {tool_id} is already in the table (each tool's id once)")
        name = row.text("name", f"tool {tool_id}")
        sections = row.section("sections")
        for section in sections.mapping:
            if section in CELL_SECTIONS or (routine_sections is not None and section not in routine_sections):
                known = "any routine's" if routine_sections is None else ", ".join(sorted(routine_sections))
                sections.fail(section, f"no routine's section (routine sections: {known})")
            sections.section(section)  # a mapping, else refused here
        own = {str(k): dict(v) for k, v in sections.mapping.items()}
        body = Section(row.source, row.name, {k: v for k, v in row.mapping.items()
                                              if k not in ("id", "name", "sections", "frame_block")}, row.error)
        tool = _read_tool(body)
        block = row.integer("frame_block", low=0, high=TOOL_IDS[1] - 1) if "frame_block" in row else None
        tools[tool_id] = ToolSpec(tool.tcp_m, tool.axis, tool.radius_m, tool.length_m, tool.bands,
                                  tool_id, name, own, block)
        rows[tool_id] = row
    _check_frame_blocks(tools, rows)
    return tools


def _check_frame_blocks(tools: dict, rows: dict) -> None:
    """Each tool its own block: a ``frame_block`` another tool has (given, or by its place) is refused."""
    owner: dict[int, int] = {}
    for tool_id, block in tool_blocks(tools).items():
        if block in owner:
            other = owner[block]
            blamed, keeps = (tool_id, other) if tools[tool_id].frame_block is not None else (other, tool_id)
            how = "names it too" if tools[keeps].frame_block is not None else "has it by its place in the table"
            rows[blamed].fail("frame_block", f"block {block} is tool {keeps}'s (tool {keeps} {how}); each tool "
                                             "needs a block of its own: give another frame_block")
        owner[block] = tool_id


def _read_bands(s: Section) -> Bands:
    """[tool.bands]: inner below outer, both above 0; the outer band at most the plausibility
    gate's limits (a shift beyond those is never a correction)."""
    d = Bands()
    inner_mm = s.number("inner_mm", d.inner_mm, above=0.0, high=PLAUSIBLE_MM)
    inner_deg = s.number("inner_deg", d.inner_deg, above=0.0, high=PLAUSIBLE_DEG)
    outer_mm = s.number("outer_mm", d.outer_mm, above=0.0, high=PLAUSIBLE_MM)
    outer_deg = s.number("outer_deg", d.outer_deg, above=0.0, high=PLAUSIBLE_DEG)
    # between the two bands lies every correction a check may write: none left is refused, not widened
    for unit, inner, outer in (("mm", inner_mm, outer_mm), ("deg", inner_deg, outer_deg)):
        if outer > inner:
            continue
        if f"outer_{unit}" in s:
            s.fail(f"outer_{unit}", f"{outer:g} is not wider than the inner band {inner:g} {unit}: the outer band "
                                    "must be wider (between the two lie the corrections a check may write)")
        else:
            s.fail(f"inner_{unit}", f"{inner:g} is not inside the default outer band {outer:g} {unit}: give "
                                    f"outer_{unit} too, wider than it")
    # the drift alarm: optional, above 0, bounded like the bands (beyond the plausibility limit no
    # frame is ever written, so no drift that large can build up)
    drift_mm = s.number("drift_mm", above=0.0, high=PLAUSIBLE_MM) if "drift_mm" in s else None
    drift_deg = s.number("drift_deg", above=0.0, high=PLAUSIBLE_DEG) if "drift_deg" in s else None
    s.done()
    return Bands(inner_mm, inner_deg, outer_mm, outer_deg, drift_mm, drift_deg)


def _read_beams(top: Section) -> tuple[BeamSpec, ...]:
    beams = []
    for b in top.items_of("beams", nonempty=True):
        beams.append(BeamSpec(b.vector("point_m", 3, required=True), _unit(b, "direction", required=True),
                              b.number("radius_m", 0.0005, above=0.0, high=0.05),
                              b.integer("channel", 0, low=0, high=17), b.flag("level_when_blocked", True)))
        b.done()
    channels = [b.channel for b in beams]
    if len(set(channels)) != len(channels):
        top.fail("beams", f"two beams on one channel ({channels})")
    return tuple(beams)


def _read_sim_truth(s: Section) -> SimTruthSpec:
    tcp = s.vector("tool_tcp_m", 3) if "tool_tcp_m" in s else None
    axis = _unit(s, "tool_axis") if "tool_axis" in s else None
    spec = SimTruthSpec(
        seed=s.integer("seed", 0, low=0, high=2**32 - 1),
        arm_length_error_mm=s.number("arm_length_error_mm", 0.0, low=0.0, high=20.0),
        arm_angle_error_deg=s.number("arm_angle_error_deg", 0.0, low=0.0, high=2.0),
        tool_tcp_m=tcp, tool_tcp_error_mm=s.number("tool_tcp_error_mm", 1.0, low=0.0, high=50.0),
        tool_axis=axis, tool_tilt_deg=s.number("tool_tilt_deg", 0.5, low=0.0, high=10.0),
        fixture_error_mm=s.number("fixture_error_mm", 0.5, low=0.0, high=50.0),
        repeatability_mm=s.number("repeatability_mm", 0.03, low=0.0, high=5.0),
        trigger_latency_s=s.number("trigger_latency_s", 0.0, low=0.0, high=1.0),
        trigger_jitter_s=s.number("trigger_jitter_s", 0.0, low=0.0, high=0.1),
        base_error_mm=s.number("base_error_mm", 5.0, low=0.0, high=200.0),
        base_error_deg=s.number("base_error_deg", 0.5, low=0.0, high=10.0))
    s.done()
    return spec


def _read_arm(s: Section, path: Path) -> tuple[str, np.ndarray]:
    """The robot model (a shipped name, or a file next to the cell file) and its home joints."""
    robot = s.text("robot", required=True)
    if "/" in robot or robot.endswith((".yaml", ".yml")):  # a model file next to the cell file
        robot = str(path.parent / robot)
    try:
        model = load_robot(robot)
    except ModelError as exc:
        s.fail("robot", str(exc))
    home_q = s.vector("home_q_rad", model.n_joints, required=True)
    if model.joint_limits is not None:
        for i, (v, (lo, hi)) in enumerate(zip(home_q, model.joint_limits)):
            if not lo <= v <= hi:
                s.fail("home_q_rad", f"joint {i} at {v:g} rad is outside its limits {lo:g}..{hi:g}")
    return robot, home_q


def _driver(spec: Section) -> DriverSpec:
    return DriverSpec(spec.text("driver", required=True), {k: v for k, v in spec.mapping.items() if k != "driver"})


def _read_robots(top: Section, path: Path) -> dict[str, RobotSpec]:
    """[robots] of a two-robot cell: a and b, each its model, home, driver, tool and base."""
    section = top.section("robots")
    if sorted(map(str, section.mapping)) != list(ROBOT_NAMES):
        section.fail(None, f"a two-robot cell names its robots {' and '.join(ROBOT_NAMES)} "
                           f"(found: {', '.join(map(str, section.mapping)) or 'none'})")
    robots = {}
    for name in ROBOT_NAMES:
        s = section.section(name)
        robot, home_q = _read_arm(s, path)
        driver = _driver(s.section("driver", required=True))
        tool = _read_tool(s.section("tool")) if "tool" in s else None
        base = np.concatenate([s.vector("base_m", 3, [0.0, 0.0, 0.0]),
                               np.deg2rad(s.vector("base_rotvec_deg", 3, [0.0, 0.0, 0.0]))])
        if name == ROBOT_NAMES[0] and np.any(base):
            s.fail("base_m", "robot a's base is the cell frame: leave base_m and base_rotvec_deg out")
        s.done()
        robots[name] = RobotSpec(name, robot, tuple(home_q.tolist()), driver, tool, base)
    return robots


def read_cell(name_or_path: str | Path, routine_sections: Iterable[str] | None = None) -> Cell:
    """Read and check a cell file's structure; raises CellFileError naming file, section and key.

    `routine_sections` are the sections the routines own (the routine registry's
    ``sections()``): any other section not the cell file's own is refused as unknown.
    None keeps every other section as a routine's, unchecked, for a reader that runs no
    routine (the simulations). Which drivers exist and which options they take is the
    driver registry's to say, and each routine reads its own section
    (``cellcal.daemon.cells.load_cell`` checks both).
    """
    path = resolve_cell(name_or_path)
    where = str(path)
    doc = read_yaml(path, CellFileError)
    top = Section(where, None, doc, CellFileError)
    for section in _REQUIRED:
        if section not in doc:
            top.fail(None, f"section [{section}] is missing")
    if routine_sections is not None:
        routine_sections = tuple(routine_sections)
        known = CELL_SECTIONS | set(routine_sections)
        for section in doc:
            if section not in known:
                top.fail(section, f"unknown section (sections: {', '.join(sorted(known))})")

    two = "robots" in doc
    s = top.section("cell")
    name = s.text("name", path.stem)
    if two:
        for key in ("robot", "home_q_rad"):
            if key in s:
                s.fail(key, "a two-robot cell gives each robot's model and home in [robots.a] and [robots.b]")
        for key in ("tool", "tools", "mounted"):
            if key in doc:
                top.fail(key, "a two-robot cell gives each robot's one tool in [robots.a.tool] and "
                              "[robots.b.tool] (no tool table there)")
        robots = _read_robots(top, path)
    else:
        robot, home_q = _read_arm(s, path)
    s.done()

    d = top.section("drivers")
    drivers = {}
    for kind in list(d.mapping):
        if kind not in DEVICE_KINDS:
            d.fail(kind, f"unknown device kind (kinds: {', '.join(DEVICE_KINDS)})")
        if two and kind == "robot":
            d.fail(kind, "a two-robot cell gives each robot's driver in [robots.a.driver] and [robots.b.driver]")
        drivers[kind] = _driver(d.section(kind))
    if two:
        drivers["robot"] = robots["a"].driver
    elif "robot" not in drivers:
        d.fail("robot", "missing (required)")

    w = top.section("workspace")
    low, high = w.vector("min_m", 3, required=True), w.vector("max_m", 3, required=True)
    if np.any(low >= high):
        w.fail("max_m", f"{high.tolist()} must be above min_m {low.tolist()} on every axis")
    w.done()

    lim = top.section("limits")
    limits = {"tcp_speed_m_s": lim.number("tcp_speed_m_s", required=True, above=0.0, high=5.0),
              "tcp_accel_m_s2": lim.number("tcp_accel_m_s2", 2.5, above=0.0, high=50.0),
              "joint_speed_rad_s": lim.number("joint_speed_rad_s", required=True, above=0.0, high=6.3),
              "joint_accel_rad_s2": lim.number("joint_accel_rad_s2", 4.0, above=0.0, high=100.0),
              "contact_travel_m": lim.number("contact_travel_m", 0.05, above=0.0, high=0.5),
              "tool_clearance_m": lim.number("tool_clearance_m", 0.02, above=0.0, high=1.0)}
    lim.done()

    if two:
        tool = robots["a"].tool
        tools = {tool.id: tool} if tool is not None else {}
        mounted = MountedSource("file", tool.id if tool is not None else 0)
    else:
        tools, tool, mounted = _read_tool_table(top, doc, routine_sections)
        robots = {"a": RobotSpec("a", robot, tuple(home_q.tolist()), drivers["robot"], tool)}
    beams = _read_beams(top) if "beams" in doc else ()
    stylus = None
    if "stylus" in doc:
        st = top.section("stylus")
        stylus = {"centre_m": st.vector("centre_m", 3, required=True),
                  "radius_m": st.number("radius_m", 0.0005, above=0.0, high=0.05)}
        st.done()
    pivot = None
    if "pivot" in doc:
        pv = top.section("pivot")
        pivot = pv.vector("point_m", 3, required=True)
        pv.done()
    trigger = drivers.get("trigger")
    if mounted.kind == "robot_inputs" and trigger is not None and trigger.name == "ur_digital_input":
        # the beams on the robot's own inputs: the tool changer's id must not share them
        wired = {int(c) for c in trigger.options.get("channels", ())} | {b.channel for b in beams}
        shared = sorted(wired & set(mounted.bits))
        if shared:
            Section(where, "mounted", doc["mounted"], CellFileError).fail(
                "robot_inputs", f"input {shared[0]} carries the trigger (drivers.trigger ur_digital_input, the "
                                "beams' channels) and cannot carry the tool changer's id too")
    truth = _read_sim_truth(top.section("sim_truth")) if "sim_truth" in doc else None
    if truth is not None and tools and 1 not in tools:
        for key in ("tool_tcp_m", "tool_axis"):
            if key in doc["sim_truth"]:
                Section(where, "sim_truth", doc["sim_truth"], CellFileError).fail(
                    key, f"states tool 1's real frame, and [tools] has no tool 1 (its tools: "
                         f"{', '.join(map(str, tools))}); leave it out to draw each tool's")
    routines = {}
    for section in doc if routine_sections is None else routine_sections:
        if section in doc and section not in CELL_SECTIONS:
            routines[section] = top.section(section).mapping
    a = robots["a"]
    status_page = _read_status_page(top)
    _check_status_port(top, status_page, drivers)
    plant = _read_plant(top, name, path) if "plant" in doc else PlantSpec()
    return Cell(where, name, a.robot, a.home_q_rad, drivers, low, high, limits, tool, beams, stylus,
                pivot, truth, merged_sections(routines, tool), robots, tools, routines, mounted, status_page, plant)


def _read_tool_table(top: Section, doc: dict, routine_sections) -> tuple[dict[int, ToolSpec], ToolSpec | None]:
    """A one-robot cell's tools (``tool``: a table of one, id 1; ``tools``: the table) and
    the mounted one (``mounted``, default the table's first)."""
    if "tool" in doc and "tools" in doc:
        top.fail("tools", "give either one tool ([tool]) or a tool table ([tools]), not both")
    if "mounted" in doc and "tools" not in doc:
        top.fail("mounted", "names a tool of the tool table [tools], and this file has none")
    if "tools" in doc:
        tools = _read_tools(top, routine_sections)
        source = _read_mounted(top, tools)
        mounted = source.tool if source.kind == "file" else next(iter(tools))
        return tools, tools[mounted], source
    tool = _read_tool(top.section("tool")) if "tool" in doc else None
    return ({tool.id: tool} if tool is not None else {}), tool, MountedSource("file", 1 if tool is not None else 0)


def _read_mounted(top: Section, tools: dict) -> "MountedSource":
    """[mounted]: a tool id (fixed), ``panel`` (the panel's mounted-tool register) or
    ``{robot_inputs: [bit, ...]}`` (the tool changer's id on the robot's digital inputs)."""
    have = ", ".join(map(str, tools))
    value = top.raw("mounted", next(iter(tools)))
    if value == "panel":
        return MountedSource("panel")
    if isinstance(value, dict):
        inputs = Section(top.source, "mounted", value, top.error)
        bits = inputs.sequence("robot_inputs", required=True, nonempty=True)
        inputs.done()
        if len(bits) > 8 or any(not isinstance(b, int) or isinstance(b, bool) or not 0 <= b <= ROBOT_INPUT_BITS - 1
                                for b in bits) or len(set(bits)) != len(bits):
            inputs.fail("robot_inputs", f"{bits!r}: expected up to 8 different digital input numbers in "
                                        f"0..{ROBOT_INPUT_BITS - 1}, the tool id's bits, least significant first "
                                        "(a UR: 0-7 standard, 8-15 configurable, 16-17 tool inputs)")
        largest = 2 ** len(bits) - 1
        beyond = [t for t in tools if t > largest]
        if beyond:
            inputs.fail("robot_inputs", f"{len(bits)} inputs carry tool ids up to {largest}, and [tools] has "
                                        f"tool {beyond[0]}: give more inputs or smaller ids")
        return MountedSource("robot_inputs", bits=tuple(bits))
    if not isinstance(value, int) or isinstance(value, bool):
        top.fail("mounted", f"{value!r}: expected a tool id of [tools] (its tools: {have}), `panel` (the panel's "
                            "mounted-tool register) or {robot_inputs: [...]} (the tool changer's id on the "
                            "robot's digital inputs)")
    tool_id = top.integer("mounted", value, low=TOOL_IDS[0], high=TOOL_IDS[1])
    if tool_id not in tools:
        top.fail("mounted", f"no tool {tool_id} in [tools] (its tools: {have})")
    return MountedSource("file", tool_id)
