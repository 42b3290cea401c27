"""What every named cause provides to the discrepancy analysis.

A cause contributes candidate *terms*. A term is a model extension with a few
extra physical parameters theta; all terms here act linearly:

- joint-space terms:   q_model = q_reported + B(q, context) @ theta     (B: N x joints x m)
- Cartesian terms:     p_model = p_rigid + C(q, context) @ theta        (C: N x 3 x m)
- parameter terms:     k_model = k + P(q, context) @ theta, row by row  (to first order)

so an extended fit needs only the rigid model's Jacobians (d p / d q maps B to
the measurement space). Structural changes of the rigid model itself (a Hayati
beta on nominally parallel axes) are terms that return a different model.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..measurement_model import Layout, Observations
from ..robot_model import KinematicModel


@dataclass(frozen=True)
class Context:
    """Per-measurement regressors beyond joint values (all optional but direction)."""

    direction: np.ndarray  # (N, nj) sign each joint approached the pose from, 0 unknown
    t_s: np.ndarray | None = None
    temp_c: np.ndarray | None = None
    payload_kg: np.ndarray | None = None
    dq_rad_s: np.ndarray | None = None  # (N, nj) joint velocity at the sample (trigger data)

    def subset(self, rows) -> "Context":
        pick = lambda a: None if a is None else a[rows]  # noqa: E731
        return Context(self.direction[rows], pick(self.t_s), pick(self.temp_c), pick(self.payload_kg),
                       pick(self.dq_rad_s))


def approach_directions(q: np.ndarray) -> np.ndarray:
    """Sign of each joint's last change before every row; 0 where none is known yet."""
    q = np.asarray(q, dtype=float)
    out = np.zeros_like(q)
    last = np.zeros(q.shape[1])
    for i in range(1, len(q)):
        step = np.sign(np.round(q[i] - q[i - 1], 9))
        last = np.where(step != 0, step, last)
        out[i] = last
    return out


@dataclass(frozen=True)
class Term:
    """One candidate extension: a cause at a place, with its basis."""

    cause: str
    where: dict
    names: tuple[str, ...]
    joint_basis: np.ndarray | None = None  # (N, nj, m)
    cart_basis: np.ndarray | None = None  # (N, 3, m)
    model: KinematicModel | None = None  # a structurally different rigid model (parallel_axis_tilt)
    # parameter-space terms: parameter index -> (N, m); the term moves that parameter (a frame's
    # rotation, a bending axis) by basis @ theta, row by row (trees, coupled and passive joints)
    param_basis: dict | None = None
    units: tuple[str, ...] = ()  # physical unit of each theta entry
    multi: bool = False  # the same cause at several places at once (e.g. every joint)
    extra: dict = field(default_factory=dict)

    @property
    def size(self) -> int:
        return len(self.names)

    def label(self) -> str:
        where = ", ".join(f"{k} {v}" for k, v in self.where.items())
        return f"{self.cause} ({where})" if where else self.cause


class Cause:
    """A named cause: builds its candidate terms for a data set and sizes a fit."""

    id = "none"

    def terms(self, model: KinematicModel, layout: Layout, x: np.ndarray, obs: Observations,
              ctx: Context) -> list[Term]:
        raise NotImplementedError

    def magnitude(self, term: Term, theta: np.ndarray, joint_delta: np.ndarray | None) -> dict:
        """Physical size of a fitted term, units in the key names."""
        raise NotImplementedError

    def unscorable(self, model: KinematicModel, ctx: Context) -> str | None:
        """Why these data (or this robot) cannot score the cause at all, naming what is
        missing; None when it can be scored."""
        return None
