"""Robot model files (``docs/robot-models.md``): read, validate, compile to a model.

Serial arms give ``joints`` (DH or MDH rows); trees give ``branches`` (see
:func:`tree_from_mapping`). Every problem is one :class:`ModelError` naming the file,
the section and the key. Internal units of the compiled model: mm and rad.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from cellcal.solvers.geometry.chain import Chain, Element
from cellcal.solvers.geometry.robot_model import KinematicModel, Link
from cellcal.solvers.geometry.se3 import orthonormalize
from cellcal.config.reader import ConfigError, Section, read_yaml, resolve, shipped

LENGTH_UNITS = {"mm": 1.0, "m": 1000.0}
ANGLE_UNITS = {"deg": math.pi / 180.0, "rad": 1.0}
CONVENTIONS = ("dh", "mdh")
COUPLINGS = ("none", "fanuc_j2_j3")
TOP_KEYS = {"name", "convention", "length_unit", "angle_unit", "joints", "joint_coupling",
            "joint_limits", "links", "gravity", "calibration", "effects"}  # the last two: model_files
JOINT_KEYS = {"a", "alpha", "d", "theta", "beta"}
LINK_KEYS = {"mass_kg", "com"}
TREE_KEYS = {"name", "convention", "length_unit", "angle_unit", "joint_count", "branches", "targets",
             "gravity", "calibration", "effects"}
BRANCH_KEYS = {"name", "parent", "mount", "frames", "end"}
FRAME_KEYS = {"a", "alpha", "d", "theta", "joint"}
MOUNT_KEYS = {"xyz", "matrix", "fixed"}
DEFAULT_GRAVITY = (0.0, 0.0, -9.81)


class ModelError(ConfigError):
    """A robot model that cannot be used; the message names the file and key."""


def shipped_robots() -> dict[str, Path]:
    """Robot models that ship with cellcal, by file stem (e.g. ``ur10e``)."""
    return shipped("robots")


def resolve_robot(name_or_path: str | Path) -> Path:
    """A path as given, or the name of a shipped model (``ur10e``)."""
    return resolve(name_or_path, "robots", "robot", ModelError)


def load_robot(name_or_path: str | Path) -> KinematicModel:
    """Load and validate a robot model; raises ModelError naming file and key."""
    path = resolve_robot(name_or_path)
    doc = read_yaml(path, ModelError)
    if isinstance(doc, dict) and "branches" in doc:
        return tree_from_mapping(doc, source=str(path))
    return model_from_mapping(doc, source=str(path))


def _units(top: Section) -> tuple[float, float]:
    length = LENGTH_UNITS[top.choice("length_unit", tuple(LENGTH_UNITS), required=True)]
    angle = ANGLE_UNITS[top.choice("angle_unit", tuple(ANGLE_UNITS), required=True)]
    return length, angle


def model_from_mapping(doc, source: str = "<memory>") -> KinematicModel:
    """Validate a parsed serial model file and compile it; raises ModelError."""
    top = Section(source, None, doc, ModelError).expect(
        TOP_KEYS, ("name", "convention", "length_unit", "angle_unit", "joints"))
    name = str(top.raw("name"))
    convention = top.choice("convention", CONVENTIONS, required=True)
    lu, au = _units(top)
    coupling = top.choice("joint_coupling", COUPLINGS, "none")
    joints = top.items_of("joints", required=True, nonempty=True)
    n = len(joints)
    if coupling == "fanuc_j2_j3" and n < 3:
        top.fail("joint_coupling", "fanuc_j2_j3 needs at least three joints")

    names, nominal, is_angle, elements = [], [], [], []
    joint_elements, link_ends = [], []

    def param(pname, value, angle):
        names.append(pname)
        nominal.append(value)
        is_angle.append(angle)
        return len(names) - 1

    for i, row in enumerate(joints):
        row.expect(JOINT_KEYS, ("a", "alpha", "d", "theta"))
        if "beta" in row and convention != "mdh":
            row.fail("beta", "beta (Hayati) is only defined for convention mdh")
        a, d = row.number("a") * lu, row.number("d") * lu
        alpha, theta = row.number("alpha") * au, row.number("theta") * au
        j = i + 1
        coupled = ((2, 1.0), (1, 1.0)) if coupling == "fanuc_j2_j3" and i == 2 else ((i, 1.0),)
        it = param(f"theta{j}", theta, True)
        idd = param(f"d{j}", d, False)
        ia = param(f"a{j}", a, False)
        ial = param(f"alpha{j}", alpha, True)
        if convention == "dh":
            joint_elements.append(len(elements))
            elements += [Element("rz", it, joints=coupled), Element("tz", idd),
                         Element("tx", ia), Element("rx", ial)]
        else:
            elements += [Element("rx", ial), Element("tx", ia)]
            joint_elements.append(len(elements))
            elements += [Element("rz", it, joints=coupled), Element("tz", idd)]
            if "beta" in row:
                ib = param(f"beta{j}", row.number("beta") * au, True)
                elements.append(Element("ry", ib))
        link_ends.append(len(elements))

    limits = None
    if "joint_limits" in top:
        raw = top.sequence("joint_limits")
        if len(raw) != n:
            top.fail("joint_limits", f"expected {n} [low, high] pairs (one per joint), got {len(raw)}")
        pairs = Section(source, "joint_limits", {f"[{i}]": r for i, r in enumerate(raw)}, ModelError)
        limits = np.array([pairs.vector(f"[{i}]", 2) for i in range(n)]) * au
        for i, (lo, hi) in enumerate(limits):
            if lo >= hi:
                pairs.fail(f"[{i}]", "low must be below high")

    links: tuple[Link, ...] = ()
    if "links" in top:
        rows = top.items_of("links")
        if len(rows) != n:
            top.fail("links", f"expected {n} entries (one per joint), got {len(rows)}")
        out = []
        for row in rows:
            row.expect(LINK_KEYS)
            mass = row.number("mass_kg", low=0.0) if "mass_kg" in row else None
            com = row.vector("com", 3) * lu if "com" in row else None
            out.append(Link(mass, com))
        links = tuple(out)

    return KinematicModel(
        name=name, convention=convention, n_joints=n, param_names=tuple(names), nominal=np.array(nominal),
        param_is_angle=np.array(is_angle), chains={"flange": Chain(tuple(elements))}, joint_limits=limits,
        links=links, gravity=top.vector("gravity", 3, DEFAULT_GRAVITY), source=source,
        joint_elements=tuple(joint_elements), link_ends=tuple(link_ends))


# -- trees ---------------------------------------------------------------------------------------

def _transform(spec: Section, lu: float) -> tuple[np.ndarray, bool]:
    """A fixed transform from {xyz: [...]} or {matrix: 3x4}; returns (4x4 in mm, fixed?)."""
    spec.expect(MOUNT_KEYS)
    out = np.eye(4)
    if "matrix" in spec:
        rows = spec.sequence("matrix")
        if len(rows) != 3:
            spec.fail("matrix", "expected 3 rows of 4 numbers")
        m_rows = Section(spec.source, spec.child_name("matrix"), {f"[{i}]": r for i, r in enumerate(rows)},
                         ModelError)
        m = np.array([m_rows.vector(f"[{i}]", 4) for i in range(3)])
        out[:3, :3] = orthonormalize(m[:, :3])
        out[:3, 3] = m[:, 3] * lu
    elif "xyz" in spec:
        out[:3, 3] = spec.vector("xyz", 3) * lu
    else:
        spec.fail(None, "give xyz or matrix")
    return out, spec.flag("fixed", False)


def _joint_map(frame: Section, n_joints: int):
    """joint: 3 or {2: -1, 3: -1} -> ((index0, coefficient), ...)."""
    value = frame.raw("joint")
    if isinstance(value, int) and not isinstance(value, bool):
        pairs = {value: 1.0}
    elif isinstance(value, dict):
        coefficients = frame.section("joint")
        pairs = {k: coefficients.number(k) for k in value}
    else:
        frame.fail("joint", f"expected a joint number or a mapping joint: coefficient, got {value!r}")
    out = []
    for j, c in pairs.items():
        if not isinstance(j, int) or isinstance(j, bool) or not 1 <= j <= n_joints:
            frame.fail("joint", f"joint {j!r} is not in 1..{n_joints} (joint_count)")
        out.append((j - 1, float(c)))
    return tuple(out)


def tree_from_mapping(doc, source: str = "<memory>") -> KinematicModel:
    """Validate a parsed tree model file (branches on mounts) and compile it; raises ModelError.

    A model file with ``branches`` instead of ``joints`` describes a tree::

        convention: mdh            # every frame: Rx(alpha) Tx(a) Rz(theta + q) Tz(d)
        length_unit: m
        angle_unit: rad
        joint_count: 19            # joint values per measurement (q1 .. q19)
        branches:
          - name: torso
            mount: {xyz: [0, 0, 0.5884], fixed: true}    # after the robot base frame
            frames:
              - {a: 0, alpha: 0, theta: 0, d: 0.1055, joint: 1}
              - {..., joint: {2: -1, 3: -1}}             # passive: q = -(q2 + q3)
          - name: right
            parent: torso                                # hangs off the parent's last frame
            mount: {matrix: [[...], [...], [...]]}       # 3 x 4, rotation orthonormalised
            frames: [...]
            end: {matrix: [...]}                         # fixed frame the targets are given in
        targets: {right: right, left: left}              # target id -> branch carrying it

    Every frame's a, alpha, theta, d and every non-fixed mount's x, y, z, rz, ry, rx
    (ZYX angles of the mount rotation) are parameters named ``branch.name`` (e.g.
    ``right.theta3``, ``right.mount.ry``), numbered per branch from 1. Each leaf
    branch compiles to one chain from the base; shared frames share parameters.
    """
    top = Section(source, None, doc, ModelError).expect(
        TREE_KEYS, ("name", "convention", "length_unit", "angle_unit", "joint_count", "branches", "targets"))
    if top.choice("convention", CONVENTIONS) != "mdh":
        top.fail("convention", "tree models are written in mdh")
    lu, au = _units(top)
    n_joints = top.integer("joint_count", low=1)

    names, nominal, is_angle = [], [], []

    def param(name, value, angle):
        names.append(name)
        nominal.append(value)
        is_angle.append(angle)
        return len(names) - 1

    branch_elements: dict[str, list[Element]] = {}
    parents: dict[str, str | None] = {}
    ends: dict[str, np.ndarray] = {}
    for branch in top.items_of("branches", required=True, nonempty=True):
        branch.expect(BRANCH_KEYS)
        name = branch.raw("name")
        if not isinstance(name, str) or not name or name in branch_elements:
            branch.fail("name", f"expected a new branch name, got {name!r}")
        parent = branch.raw("parent")
        if parent is not None and parent not in branch_elements:
            branch.fail("parent", f"{parent!r} is not a branch defined above")
        elements: list[Element] = []
        if "mount" in branch:
            mount, fixed = _transform(branch.section("mount"), lu)
            from scipy.spatial.transform import Rotation  # imported here: 0.17 s a process that never needs it
            angles = Rotation.from_matrix(mount[:3, :3]).as_euler("ZYX")
            values = [("x", "tx", mount[0, 3], False), ("y", "ty", mount[1, 3], False),
                      ("z", "tz", mount[2, 3], False), ("rz", "rz", angles[0], True),
                      ("ry", "ry", angles[1], True), ("rx", "rx", angles[2], True)]
            for pname, kind, value, angle in values:
                if fixed:
                    elements.append(Element(kind, constant=float(value)))
                else:
                    elements.append(Element(kind, param(f"{name}.mount.{pname}", float(value), angle)))
        for i, frame in enumerate(branch.items_of("frames")):
            frame.expect(FRAME_KEYS, ("a", "alpha", "d", "theta"))
            joints = _joint_map(frame, n_joints) if "joint" in frame else ()
            j = i + 1
            elements += [
                Element("rx", param(f"{name}.alpha{j}", frame.number("alpha") * au, True)),
                Element("tx", param(f"{name}.a{j}", frame.number("a") * lu, False)),
                Element("rz", param(f"{name}.theta{j}", frame.number("theta") * au, True), joints=joints),
                Element("tz", param(f"{name}.d{j}", frame.number("d") * lu, False)),
            ]
        branch_elements[name] = elements
        parents[name] = parent
        if "end" in branch:
            ends[name] = _transform(branch.section("end"), lu)[0]

    leaves = [b for b in branch_elements if b not in parents.values()]
    chains = {}
    for leaf in leaves:
        path, b = [], leaf
        while b is not None:
            path.insert(0, b)
            b = parents[b]
        chains[leaf] = Chain(tuple(e for b in path for e in branch_elements[b]), ends.get(leaf, np.eye(4)))

    targets = top.section("targets", required=True)
    if not targets.mapping:
        top.fail("targets", "expected a mapping target id -> branch")
    for t, b in targets.mapping.items():
        if b not in chains:
            targets.fail(t, f"{b!r} is not a leaf branch (leaves: {', '.join(leaves)})")
    return KinematicModel(
        name=str(top.raw("name")), convention="mdh", n_joints=n_joints, param_names=tuple(names),
        nominal=np.array(nominal), param_is_angle=np.array(is_angle), chains=chains,
        target_chains={str(t): b for t, b in targets.mapping.items()}, default_chain=leaves[0],
        gravity=top.vector("gravity", 3, DEFAULT_GRAVITY), source=source)
