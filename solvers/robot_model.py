"""Robot models: nominal geometry compiled to parameterised kinematic chains.

A model file (``spec/robot-model.md``) is parsed elsewhere (YAML is IO); this
module validates the parsed mapping and compiles it. Internal units: mm and rad.

Parameter names are ``theta1``, ``d1``, ``a1``, ``alpha1`` (and ``beta1`` for
MDH joints whose file gives a Hayati beta), numbered from 1 at the base.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from .chain import Chain, Element

LENGTH_UNITS = {"mm": 1.0, "m": 1000.0}
ANGLE_UNITS = {"deg": math.pi / 180.0, "rad": 1.0}
CONVENTIONS = ("dh", "mdh")
COUPLINGS = ("none", "fanuc_j2_j3")
TOP_KEYS = {"name", "convention", "length_unit", "angle_unit", "joints", "joint_coupling",
            "joint_limits", "links", "gravity"}
JOINT_KEYS = {"a", "alpha", "d", "theta", "beta"}
LINK_KEYS = {"mass_kg", "com"}


class ModelError(ValueError):
    """A robot model that cannot be used; the message names the file and key."""


@dataclass(frozen=True)
class Link:
    mass_kg: float | None
    com_mm: np.ndarray | None  # centre of mass in the link frame


@dataclass(frozen=True)
class KinematicModel:
    """Compiled robot: chains over a named parameter vector (mm, rad)."""

    name: str
    convention: str
    n_joints: int
    param_names: tuple[str, ...]
    nominal: np.ndarray
    param_is_angle: np.ndarray
    chains: dict[str, Chain]
    target_chains: dict[str, str] = field(default_factory=dict)  # target id -> chain name
    default_chain: str = "flange"
    joint_limits: np.ndarray | None = None  # (n_joints, 2) rad
    links: tuple[Link, ...] = ()
    gravity: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -9.81]))
    source: str = "<memory>"
    # in the default chain: index of each joint's rotation element, and the element
    # count after which each link's own frame (the frame its centre of mass is given in) stands
    joint_elements: tuple[int, ...] = ()
    link_ends: tuple[int, ...] = ()

    @property
    def n_params(self) -> int:
        return len(self.param_names)

    def chain_for(self, target: str) -> str:
        return self.target_chains.get(target, self.default_chain)

    def index(self, name: str) -> int:
        return self.param_names.index(name)


def _fail(source: str, key: str, msg: str):
    raise ModelError(f"{source}: {key}: {msg}")


def _number(source, key, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        _fail(source, key, f"expected a number, got {value!r}")
    if not math.isfinite(value):
        _fail(source, key, f"expected a finite number, got {value!r}")
    return float(value)


def _vector(source, key, value, n) -> np.ndarray:
    if not isinstance(value, (list, tuple)) or len(value) != n:
        _fail(source, key, f"expected a list of {n} numbers, got {value!r}")
    return np.array([_number(source, f"{key}[{i}]", v) for i, v in enumerate(value)])


def _check_mapping(source, key, value, allowed, required=(), what="a mapping"):
    """A mapping with only known keys and every required one; names the offending key."""
    if not isinstance(value, dict):
        _fail(source, key, f"expected {what}, got {value!r}")
    bad = sorted(set(value) - set(allowed))
    if bad:
        _fail(source, f"{key}.{bad[0]}" if key else bad[0], f"unknown key (allowed: {', '.join(sorted(allowed))})")
    for k in required:
        if k not in value:
            _fail(source, f"{key}.{k}" if key else k, "required key is missing")
    return value


def _choice(source, key, value, allowed):
    if value not in allowed:
        _fail(source, key, f"expected one of {', '.join(allowed)}, got {value!r}")
    return value


def model_from_mapping(doc, source: str = "<memory>") -> KinematicModel:
    """Validate a parsed model file and compile it; raises ModelError."""
    if not isinstance(doc, dict):
        raise ModelError(f"{source}: expected a mapping at top level, got {type(doc).__name__}")
    _check_mapping(source, "", doc, TOP_KEYS, ("name", "convention", "length_unit", "angle_unit", "joints"))
    name = str(doc["name"])
    convention = _choice(source, "convention", doc["convention"], CONVENTIONS)
    lu = LENGTH_UNITS[_choice(source, "length_unit", doc["length_unit"], tuple(LENGTH_UNITS))]
    au = ANGLE_UNITS[_choice(source, "angle_unit", doc["angle_unit"], tuple(ANGLE_UNITS))]
    coupling = _choice(source, "joint_coupling", doc.get("joint_coupling", "none"), COUPLINGS)

    joints = doc["joints"]
    if not isinstance(joints, list) or not joints:
        _fail(source, "joints", "expected a non-empty list of joints")
    n = len(joints)
    if coupling == "fanuc_j2_j3" and n < 3:
        _fail(source, "joint_coupling", "fanuc_j2_j3 needs at least three joints")

    names, nominal, is_angle, elements = [], [], [], []
    joint_elements, link_ends = [], []

    def param(pname, value, angle):
        names.append(pname)
        nominal.append(value)
        is_angle.append(angle)
        return len(names) - 1

    for i, row in enumerate(joints):
        key = f"joints[{i}]"
        _check_mapping(source, key, row, JOINT_KEYS, ("a", "alpha", "d", "theta"),
                       "a mapping with keys a, alpha, d, theta")
        if "beta" in row and convention != "mdh":
            _fail(source, f"{key}.beta", "beta (Hayati) is only defined for convention mdh")
        a = _number(source, f"{key}.a", row["a"]) * lu
        d = _number(source, f"{key}.d", row["d"]) * lu
        alpha = _number(source, f"{key}.alpha", row["alpha"]) * au
        theta = _number(source, f"{key}.theta", row["theta"]) * au
        j = i + 1
        coupled = ((i, 1.0),)
        if coupling == "fanuc_j2_j3" and i == 2:
            coupled = ((2, 1.0), (1, 1.0))
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
                ib = param(f"beta{j}", _number(source, f"{key}.beta", row["beta"]) * au, True)
                elements.append(Element("ry", ib))
        link_ends.append(len(elements))

    limits = None
    if "joint_limits" in doc:
        raw = doc["joint_limits"]
        if not isinstance(raw, list) or len(raw) != n:
            _fail(source, "joint_limits", f"expected {n} [low, high] pairs (one per joint), got "
                  f"{len(raw) if isinstance(raw, list) else raw!r}")
        limits = np.array([_vector(source, f"joint_limits[{i}]", r, 2) for i, r in enumerate(raw)]) * au
        for i, (lo, hi) in enumerate(limits):
            if lo >= hi:
                _fail(source, f"joint_limits[{i}]", "low must be below high")

    links: tuple[Link, ...] = ()
    if "links" in doc:
        raw = doc["links"]
        if not isinstance(raw, list) or len(raw) != n:
            _fail(source, "links", f"expected {n} entries (one per joint), got "
                  f"{len(raw) if isinstance(raw, list) else raw!r}")
        out = []
        for i, row in enumerate(raw):
            if not isinstance(row, dict):
                _fail(source, f"links[{i}]", "expected a mapping with mass_kg and com")
            bad = sorted(set(row) - LINK_KEYS)
            if bad:
                _fail(source, f"links[{i}].{bad[0]}", "unknown key (allowed: com, mass_kg)")
            mass = _number(source, f"links[{i}].mass_kg", row["mass_kg"]) if "mass_kg" in row else None
            if mass is not None and mass < 0:
                _fail(source, f"links[{i}].mass_kg", "mass must not be negative")
            com = _vector(source, f"links[{i}].com", row["com"], 3) * lu if "com" in row else None
            out.append(Link(mass, com))
        links = tuple(out)

    gravity = np.array([0.0, 0.0, -9.81])
    if "gravity" in doc:
        gravity = _vector(source, "gravity", doc["gravity"], 3)

    return KinematicModel(
        name=name,
        convention=convention,
        n_joints=n,
        param_names=tuple(names),
        nominal=np.array(nominal),
        param_is_angle=np.array(is_angle),
        chains={"flange": Chain(tuple(elements))},
        joint_limits=limits,
        links=links,
        gravity=gravity,
        source=source,
        joint_elements=tuple(joint_elements),
        link_ends=tuple(link_ends),
    )


PARALLEL_TOL_RAD = np.deg2rad(1.0)


def parallel_joint_pairs(model: KinematicModel) -> list[int]:
    """Joints i (0-based) whose axis is nominally parallel to joint i+1's."""
    out = []
    for i in range(model.n_joints - 1):
        alpha = model.nominal[model.index(f"alpha{i + (1 if model.convention == 'dh' else 2)}")]
        if abs(np.sin(alpha)) < np.sin(PARALLEL_TOL_RAD):
            out.append(i)
    return out


def with_hayati_beta(model: KinematicModel, joint: int) -> KinematicModel:
    """The same model with a Hayati beta (rotation about y) closing joint `joint` (0-based).

    That tilt between nominally parallel axes is what classic DH cannot represent.
    """
    name = f"beta{joint + 1}"
    if name in model.param_names:
        raise ValueError(f"{model.name}: already has {name}")
    at = model.link_ends[joint]
    chain = model.chains[model.default_chain]
    elements = list(chain.elements)
    elements.insert(at, Element("ry", model.n_params))
    return replace(
        model,
        param_names=model.param_names + (name,),
        nominal=np.append(model.nominal, 0.0),
        param_is_angle=np.append(model.param_is_angle, True),
        chains={**model.chains, model.default_chain: Chain(tuple(elements), chain.end)},
        joint_elements=tuple(e + (e >= at) for e in model.joint_elements),
        link_ends=tuple(e + (e >= at) if i != joint else e + 1 for i, e in enumerate(model.link_ends)),
    )
