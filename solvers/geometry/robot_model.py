"""Robot models: nominal geometry compiled to parameterised kinematic chains.

Model files (``docs/robot-models.md``) are read and compiled by
``cellcal.config.robot_files``; this module holds the compiled model and what the
solvers derive from it. Internal units: mm and rad.

Parameter names are ``theta1``, ``d1``, ``a1``, ``alpha1`` (and ``beta1`` for
MDH joints whose file gives a Hayati beta), numbered from 1 at the base.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from cellcal.solvers.geometry.chain import Chain, Element


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
