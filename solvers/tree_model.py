"""Tree-structured robots: branches (torso, arms) on fixed mounts, coupled joints.

A model file with ``branches`` instead of ``joints`` describes a tree:

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
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from .chain import Chain, Element
from .robot_model import (ANGLE_UNITS, CONVENTIONS, LENGTH_UNITS, KinematicModel, _check_mapping, _choice,
                          _fail, _number, _vector)
from .se3 import orthonormalize

TREE_KEYS = {"name", "convention", "length_unit", "angle_unit", "joint_count", "branches", "targets",
             "gravity"}
BRANCH_KEYS = {"name", "parent", "mount", "frames", "end"}
FRAME_KEYS = {"a", "alpha", "d", "theta", "joint"}
MOUNT_KEYS = {"xyz", "matrix", "fixed"}


def _transform(source, key, spec, lu) -> tuple[np.ndarray, bool]:
    """A fixed transform from {xyz: [...]} or {matrix: 3x4}; returns (4x4 in mm, fixed?)."""
    _check_mapping(source, key, spec, MOUNT_KEYS, what="a mapping with xyz or matrix")
    out = np.eye(4)
    if "matrix" in spec:
        rows = spec["matrix"]
        if not isinstance(rows, list) or len(rows) != 3:
            _fail(source, f"{key}.matrix", "expected 3 rows of 4 numbers")
        m = np.array([_vector(source, f"{key}.matrix[{i}]", r, 4) for i, r in enumerate(rows)])
        out[:3, :3] = orthonormalize(m[:, :3])
        out[:3, 3] = m[:, 3] * lu
    elif "xyz" in spec:
        out[:3, 3] = _vector(source, f"{key}.xyz", spec["xyz"], 3) * lu
    else:
        _fail(source, key, "give xyz or matrix")
    return out, bool(spec.get("fixed", False))


def _joint_map(source, key, value, n_joints):
    """joint: 3 or {2: -1, 3: -1} -> ((index0, coefficient), ...)."""
    if isinstance(value, int) and not isinstance(value, bool):
        pairs = {value: 1.0}
    elif isinstance(value, dict):
        pairs = {k: _number(source, f"{key}[{k}]", v) for k, v in value.items()}
    else:
        _fail(source, key, f"expected a joint number or a mapping joint: coefficient, got {value!r}")
    out = []
    for j, c in pairs.items():
        if not isinstance(j, int) or not 1 <= j <= n_joints:
            _fail(source, key, f"joint {j!r} is not in 1..{n_joints} (joint_count)")
        out.append((j - 1, float(c)))
    return tuple(out)


def tree_from_mapping(doc: dict, source: str = "<memory>") -> KinematicModel:
    _check_mapping(source, "", doc, TREE_KEYS,
                   ("name", "convention", "length_unit", "angle_unit", "joint_count", "branches", "targets"))
    if _choice(source, "convention", doc["convention"], CONVENTIONS) != "mdh":
        _fail(source, "convention", "tree models are written in mdh")
    lu = LENGTH_UNITS[_choice(source, "length_unit", doc["length_unit"], tuple(LENGTH_UNITS))]
    au = ANGLE_UNITS[_choice(source, "angle_unit", doc["angle_unit"], tuple(ANGLE_UNITS))]
    n_joints = doc["joint_count"]
    if not isinstance(n_joints, int) or n_joints < 1:
        _fail(source, "joint_count", f"expected a positive whole number, got {n_joints!r}")

    names, nominal, is_angle = [], [], []

    def param(name, value, angle):
        names.append(name)
        nominal.append(value)
        is_angle.append(angle)
        return len(names) - 1

    branch_elements: dict[str, list[Element]] = {}
    parents: dict[str, str | None] = {}
    ends: dict[str, np.ndarray] = {}
    raw = doc["branches"]
    if not isinstance(raw, list) or not raw:
        _fail(source, "branches", "expected a list of branches")
    for b, branch in enumerate(raw):
        key = f"branches[{b}]"
        _check_mapping(source, key, branch, BRANCH_KEYS)
        name = branch.get("name")
        if not isinstance(name, str) or not name or name in branch_elements:
            _fail(source, f"{key}.name", f"expected a new branch name, got {name!r}")
        parent = branch.get("parent")
        if parent is not None and parent not in branch_elements:
            _fail(source, f"{key}.parent", f"{parent!r} is not a branch defined above")
        elements: list[Element] = []
        if "mount" in branch:
            mount, fixed = _transform(source, f"{key}.mount", branch["mount"], lu)
            angles = Rotation.from_matrix(mount[:3, :3]).as_euler("ZYX")
            values = [("x", "tx", mount[0, 3], False), ("y", "ty", mount[1, 3], False),
                      ("z", "tz", mount[2, 3], False), ("rz", "rz", angles[0], True),
                      ("ry", "ry", angles[1], True), ("rx", "rx", angles[2], True)]
            for pname, kind, value, angle in values:
                if fixed:
                    elements.append(Element(kind, constant=float(value)))
                else:
                    elements.append(Element(kind, param(f"{name}.mount.{pname}", float(value), angle)))
        frames = branch.get("frames", [])
        if not isinstance(frames, list):
            _fail(source, f"{key}.frames", "expected a list of frames")
        for i, row in enumerate(frames):
            fkey = f"{key}.frames[{i}]"
            _check_mapping(source, fkey, row, FRAME_KEYS, ("a", "alpha", "d", "theta"),
                           "a mapping with a, alpha, theta, d, joint")
            joints = _joint_map(source, f"{fkey}.joint", row["joint"], n_joints) if "joint" in row else ()
            j = i + 1
            elements += [
                Element("rx", param(f"{name}.alpha{j}", _number(source, f"{fkey}.alpha", row["alpha"]) * au, True)),
                Element("tx", param(f"{name}.a{j}", _number(source, f"{fkey}.a", row["a"]) * lu, False)),
                Element("rz", param(f"{name}.theta{j}", _number(source, f"{fkey}.theta", row["theta"]) * au, True),
                        joints=joints),
                Element("tz", param(f"{name}.d{j}", _number(source, f"{fkey}.d", row["d"]) * lu, False)),
            ]
        branch_elements[name] = elements
        parents[name] = parent
        if "end" in branch:
            ends[name] = _transform(source, f"{key}.end", branch["end"], lu)[0]

    leaves = [b for b in branch_elements if b not in parents.values()]
    chains = {}
    for leaf in leaves:
        path, b = [], leaf
        while b is not None:
            path.insert(0, b)
            b = parents[b]
        chains[leaf] = Chain(tuple(e for b in path for e in branch_elements[b]), ends.get(leaf, np.eye(4)))

    targets = doc["targets"]
    if not isinstance(targets, dict) or not targets:
        _fail(source, "targets", "expected a mapping target id -> branch")
    for t, b in targets.items():
        if b not in chains:
            _fail(source, f"targets.{t}", f"{b!r} is not a leaf branch (leaves: {', '.join(leaves)})")
    gravity = np.array([0.0, 0.0, -9.81])
    if "gravity" in doc:
        gravity = _vector(source, "gravity", doc["gravity"], 3)
    return KinematicModel(
        name=str(doc["name"]), convention="mdh", n_joints=n_joints, param_names=tuple(names),
        nominal=np.array(nominal), param_is_angle=np.array(is_angle), chains=chains,
        target_chains={str(t): b for t, b in targets.items()}, default_chain=leaves[0],
        gravity=gravity, source=source)
