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

from cellcal.solvers.identification.measurement_model import Layout, Observations
from cellcal.solvers.geometry.robot_model import KinematicModel


@dataclass(frozen=True)
class Context:
    """Per-measurement regressors beyond joint values (all optional but direction)."""

    direction: np.ndarray  # (N, nj) sign each joint approached the pose from, 0 unknown
    t_s: np.ndarray | None = None
    temp_c: np.ndarray | None = None
    payload_kg: np.ndarray | None = None
    dq_rad_s: np.ndarray | None = None  # (N, nj) joint velocity at the sample (trigger data)
    folds: np.ndarray | None = None  # the analysis' fold of each row (crossval.FoldIds): a cause that chooses
    #                                  among its terms by the data does so again inside each fold's training

    def subset(self, rows) -> "Context":
        pick = lambda a: None if a is None else a[rows]  # noqa: E731
        return Context(self.direction[rows], pick(self.t_s), pick(self.temp_c), pick(self.payload_kg),
                       pick(self.dq_rad_s))


def approach_directions(q: np.ndarray) -> np.ndarray:
    """Sign of each joint's last change before every row; 0 where none is known yet."""
    q = np.asarray(q, dtype=float)
    out = np.zeros_like(q)
    if len(q) < 2:
        return out
    step = np.sign(np.round(np.diff(q, axis=0), 9))  # step[i]: from row i to row i + 1
    moved = np.where(step != 0, np.arange(1, len(q))[:, None], 0)
    last = np.maximum.accumulate(moved, axis=0)  # row after the last change, 0 for none yet
    out[1:] = np.where(last > 0, np.take_along_axis(step, np.maximum(last - 1, 0), axis=0), 0.0)
    return out


class JointBasis:
    """A joint-space basis B (N, nj, m) kept as its non-zero parts: B[n] = sum_r values[n, r] * mix[r].

    A term on one joint stores one column of values per parameter instead of N x nj x m
    numbers that are zero but for one joint. Rows are picked with ``basis[rows]`` (a
    JointBasis again); ``np.asarray(basis)`` gives the dense array.
    """

    def __init__(self, values: np.ndarray, mix: np.ndarray):
        self.values = np.asarray(values, dtype=float)  # (N, r)
        self.mix = np.asarray(mix, dtype=float)  # (r, nj, m)

    @classmethod
    def single(cls, values: np.ndarray, joint: int, n_joints: int) -> "JointBasis":
        """Column k of values moves joint `joint` (0-based), one parameter per column."""
        values = np.asarray(values, dtype=float).reshape(len(values), -1)
        m = values.shape[1]
        mix = np.zeros((m, n_joints, m))
        mix[np.arange(m), joint, np.arange(m)] = 1.0
        return cls(values, mix)

    @classmethod
    def dense_array(cls, basis: np.ndarray) -> "JointBasis":
        basis = np.asarray(basis, dtype=float)
        n, nj, m = basis.shape
        return cls(basis.reshape(n, nj * m), np.eye(nj * m).reshape(nj * m, nj, m))

    @classmethod
    def side_by_side(cls, parts, n_rows: int, n_joints: int) -> "JointBasis":
        """Bases (or None for m zero columns) given as (basis, m) pairs, columns side by side."""
        m_all = sum(m for _, m in parts)
        r_all = sum(b.values.shape[1] for b, _ in parts if b is not None)
        values, mix = np.zeros((n_rows, r_all)), np.zeros((r_all, n_joints, m_all))
        r = col = 0
        for b, m in parts:
            if b is not None:
                k = b.values.shape[1]
                values[:, r: r + k] = b.values
                mix[r: r + k, :, col: col + m] = b.mix
                r += k
            col += m
        return cls(values, mix)

    @classmethod
    def of_angle(cls, angles: np.ndarray, values_of, joint: int, n_joints: int, m: int) -> "JointBasis":
        """``single`` with values_of(angles) (N, m) computed only for the rows asked for: a basis of
        many columns over a large data set is never held whole."""
        return _AngleBasis(np.asarray(angles, dtype=float), values_of, cls.single(np.zeros((1, m)), joint,
                                                                                  n_joints).mix)

    @property
    def shape(self) -> tuple[int, int, int]:
        return (len(self.values),) + self.mix.shape[1:]

    ndim = 3

    def __len__(self) -> int:
        return len(self.values)

    def __getitem__(self, index):
        if isinstance(index, tuple):
            return self.dense()[index]
        return JointBasis(self.values[index], self.mix)

    def dense(self) -> np.ndarray:
        return np.einsum("nr,rjm->njm", self.values, self.mix)

    def __array__(self, dtype=None, copy=None):
        return self.dense() if dtype is None else self.dense().astype(dtype)

    def delta(self, theta: np.ndarray) -> np.ndarray:
        """(N, nj) joint displacement B @ theta."""
        per_value = self.mix @ np.asarray(theta, dtype=float)  # (r, nj)
        return self.values @ per_value if len(per_value) else np.zeros((len(self.values), self.mix.shape[1]))

    def columns(self, jq: np.ndarray) -> np.ndarray:
        """d p / d theta = (d p / d q) @ B, (N, 3, m), from d p / d q (N, 3, nj) of the same rows."""
        out = np.zeros(jq.shape[:2] + self.mix.shape[2:])
        for r, j, m in zip(*np.nonzero(self.mix)):  # a handful: one per parameter and joint it moves
            out[:, :, m] += (self.mix[r, j, m] * self.values[:, r])[:, None] * jq[:, :, j]
        return out


class _AngleBasis(JointBasis):
    """A JointBasis whose values are a function of one joint's angles, evaluated on demand."""

    def __init__(self, angles: np.ndarray, values_of, mix: np.ndarray):
        self.angles, self.values_of, self.mix = angles, values_of, mix

    @property
    def values(self) -> np.ndarray:
        return self.values_of(self.angles)

    @property
    def shape(self) -> tuple[int, int, int]:
        return (len(self.angles),) + self.mix.shape[1:]

    def __len__(self) -> int:
        return len(self.angles)

    def __getitem__(self, index):
        if isinstance(index, tuple):
            return self.dense()[index]
        return JointBasis(self.values_of(self.angles[index]), self.mix)


@dataclass(frozen=True)
class Term:
    """One candidate extension: a cause at a place, with its basis."""

    cause: str
    where: dict
    names: tuple[str, ...]
    joint_basis: JointBasis | None = None  # (N, nj, m); a dense array is converted
    cart_basis: np.ndarray | None = None  # (N, 3, m)
    model: KinematicModel | None = None  # a structurally different rigid model (parallel_axis_tilt)
    # parameter-space terms: parameter index -> (N, m); the term moves that parameter (a frame's
    # rotation, a bending axis) by basis @ theta, row by row (trees, coupled and passive joints)
    param_basis: dict | None = None
    units: tuple[str, ...] = ()  # physical unit of each theta entry
    multi: bool = False  # the same cause at several places at once (e.g. every joint)
    extra: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.joint_basis is not None and not isinstance(self.joint_basis, JointBasis):
            object.__setattr__(self, "joint_basis", JointBasis.dense_array(self.joint_basis))

    @property
    def size(self) -> int:
        return len(self.names)

    def label(self) -> str:
        where = ", ".join(f"{k} {v}" for k, v in self.where.items())
        return f"{self.cause} ({where})" if where else self.cause


def penalised_parts(terms) -> list[tuple["Term", float]]:
    """(part, lam) of every part of these terms (a combined term's ``extra["parts"]``) that carries a penalty
    of its own (``extra["penalty_weight"]``: a periodic spline, ``periodic_spline``), in the terms' order."""
    return [(part, float(part.extra["penalty_weight"])) for t in terms for part in t.extra.get("parts", (t,))
            if "penalty_weight" in part.extra]


def part_penalty(part: "Term", lam: float, diagonal: np.ndarray, kept: np.ndarray) -> np.ndarray:
    """(..., n, n) the penalty on a part's coefficients `kept` (indices into its own: those a fit estimates, the
    rest held at 0) from the normal matrices' diagonals over them (..., n): lam times their mean (the
    coefficients' mean squared column length over the fit's rows) times the part's roughness at kept
    (``extra["roughness"]``: the quadratic form of its coefficients that the penalty weighs; none: a ridge)."""
    diagonal = np.asarray(diagonal, dtype=float)
    kept = np.asarray(kept, dtype=int)
    rough = part.extra.get("roughness")
    form = np.eye(len(kept)) if rough is None else rough[np.ix_(kept, kept)]
    if not len(kept):
        return np.zeros(diagonal.shape + (0,))
    return (lam * diagonal.mean(axis=-1))[..., None, None] * form


class Cause:
    """A named cause: builds its candidate terms for a data set and sizes a fit."""

    id = "none"

    def terms(self, model: KinematicModel, layout: Layout, x: np.ndarray, obs: Observations,
              ctx: Context) -> list[Term]:
        raise NotImplementedError

    def compose(self, terms: list[Term], scorer) -> list[Term]:
        """The candidates to rank, from this cause's scored terms; ``scorer.heldout_errors_many``
        (term sets -> held-out errors) lets a cause choose among them by cross-validation."""
        return terms

    def search_places(self, terms: list[Term]):
        """The single places among this cause's terms that the analysis' forward search combines
        (``solvers.analysis.selection``): (places that start or join a combination, places that only stand alone);
        None for a cause whose terms compete as they are."""
        return None

    def combine(self, parts: tuple[Term, ...], n_rows: int, n_joints: int) -> Term:
        """One term of several single places (joint-space terms), their columns side by side."""
        if len(parts) == 1:
            return parts[0]
        joints = [p.where["joint"] for p in parts]
        order = np.argsort(joints)
        parts = tuple(parts[i] for i in order)
        basis = JointBasis.side_by_side([(p.joint_basis, p.size) for p in parts], n_rows, n_joints)
        return Term(self.id, {"joints": sorted(joints)}, tuple(n for p in parts for n in p.names), joint_basis=basis,
                    units=tuple(u for p in parts for u in p.units), multi=True, extra={"parts": parts})

    def magnitude(self, term: Term, theta: np.ndarray, joint_delta: np.ndarray | None) -> dict:
        """Physical size of a fitted term, units in the key names."""
        raise NotImplementedError

    def details(self, term: Term, theta: np.ndarray, q: np.ndarray) -> dict | None:
        """What a fitted term needs beyond its size to be used later (e.g. a function of a joint's
        angle with the angles it is known over), as plain numbers; None when the size says it all."""
        return None

    def places(self, term: Term):
        """Where a fitted term acts, for sizes the data can be asked about one place at a time:
        ([(label, D (N, m))], {label: index of theta}) with the place's displacement D @ theta
        (rad) over the poses, and the theta entries that are a place's physical constant
        (``physical_sizes``); None for a cause without places of its own."""
        return None

    def unscorable(self, model: KinematicModel, ctx: Context) -> str | None:
        """Why these data (or this robot) cannot score the cause at all, naming what is
        missing; None when it can be scored."""
        return None
