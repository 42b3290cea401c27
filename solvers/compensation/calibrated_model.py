"""A calibrated robot: identified geometry, instrument frame, target offsets and fitted effects.

What ``identify`` or ``analyze`` found, as one object that predicts where a target is
for given joint values. The effects are the analysis' own terms (``effects``), rebuilt
at the joint values asked about from their causes' bases and applied with their
fitted parameters theta exactly as the analysis' extended model applies them
(``extended_model``):

    q_model = q + B(q) theta            (joint-space terms: compliance, backlash, cyclic error)
    k_model = k + P(q) theta            (parameter-space terms, to first order: trees)
    Hayati beta on parallel axes        (a structurally different rigid model, with the tilt in k)

Causes that are not a property of the arm's position are kept with their parameters
but not applied (``NOT_APPLIED``): a trigger's latency belongs to the instrument, and
thermal growth needs the temperature relative to the calibration's own data.
Internal units: mm and rad, as everywhere in ``solvers``.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from cellcal.solvers.geometry import se3
from cellcal.solvers.geometry.chain import forward, point_jacobians
from cellcal.solvers.analysis.effects import CAUSES, Context, Term
from cellcal.solvers.analysis.effects.cyclic_joint_error import PeriodicJointError, fitted_errors
from cellcal.solvers.analysis.effects.periodic_spline import PeriodicSpline
from cellcal.solvers.analysis.extended_model import combine_bases, param_columns
from cellcal.solvers.identification.measurement_model import Layout, Observations
from cellcal.solvers.geometry.robot_model import KinematicModel, with_hayati_beta

NOT_APPLIED = {
    "trigger_latency": "a latency of the instrument's trigger, not of the arm's position",
    "thermal_drift": "needs the temperature relative to the calibration data's own; applied at that reference (0)",
}
STRUCTURAL = "parallel_axis_tilt"
PERIODIC = "cyclic_joint_error"  # kept as its cause's PeriodicJointError: orders, coefficients, covered angles
_PAD_ROWS = 24  # configurations added to every evaluation so a cause's data screens always pass


@dataclass(frozen=True)
class Effect:
    """One fitted term: the cause, where, its parameter names and values (units per parameter)."""

    cause: str
    where: dict
    names: tuple[str, ...]
    theta: np.ndarray
    units: tuple[str, ...]
    extra: dict = field(default_factory=dict)  # whatever else the cause records (e.g. angle coverage)

    @property
    def applied(self) -> bool:
        return self.cause not in NOT_APPLIED

    @property
    def needs_payload(self) -> bool:
        return any("payload" in n for n in self.names)


@dataclass(frozen=True)
class CalibratedModel:
    """Geometry, instrument -> base frame, target offsets and effects of one calibration.

    ``model`` already carries a structural effect (a Hayati beta), so ``k`` is its full
    parameter vector; ``base`` is (t mm, rotation vector rad) with
    p_instrument = R p_base + t; ``offsets`` one row (mm, end frame) per target name.
    """

    model: KinematicModel
    k: np.ndarray
    base: np.ndarray
    target_names: tuple[str, ...]
    offsets: np.ndarray
    effects: tuple[Effect, ...] = ()

    @property
    def layout(self) -> Layout:
        return Layout(self.model, self.target_names)

    @property
    def x(self) -> np.ndarray:
        x = self.layout.initial(self.base, self.offsets)
        x[: len(self.k)] = self.k
        return x

    @property
    def applied(self) -> tuple[Effect, ...]:
        """Applied effects whose basis their cause rebuilds at any joint values."""
        return tuple(e for e in self.effects if e.applied and e.cause not in (STRUCTURAL, PERIODIC))

    @property
    def periodic(self) -> tuple[PeriodicJointError, ...]:
        """Fitted periodic joint errors, each 0 outside the angles its data covered."""
        return tuple(p for e in self.effects if e.cause == PERIODIC for p in periodic_errors(e))

    def _periodic_delta(self, q: np.ndarray) -> np.ndarray:
        out = np.zeros_like(q)
        for p in self.periodic:
            out[:, p.joint - 1] += p.delta_rad(q[:, p.joint - 1])
        return out

    @property
    def joint_effects_only(self) -> bool:
        """Do the applied effects act through the joint values alone (no Cartesian or parameter terms)?"""
        if not self.applied:
            return True
        q = _pad_rows(self.model.n_joints)
        return all(t.cart_basis is None and not t.param_basis for t in self.terms_at(q))

    def terms_at(self, q: np.ndarray, ctx: Context | None = None) -> list[Term]:
        """The applied effects' terms at joint values q (N, nj), in ``applied`` order.

        Each cause builds its candidate terms as the analysis does; a fixed spread of
        configurations is appended first so that screens meant for a data set (a joint
        that barely moves, a side never approached from) never drop the fitted term.
        """
        q = np.atleast_2d(np.asarray(q, dtype=float))
        n, nj = q.shape
        if not self.applied:
            return []
        pad = _pad_rows(nj)
        ctx = ctx or Context(direction=np.zeros_like(q))
        payload = None
        if any(e.needs_payload for e in self.applied):
            given = np.zeros(n) if ctx.payload_kg is None else np.broadcast_to(ctx.payload_kg, (n,))
            payload = np.concatenate([given, np.linspace(0.0, 1.0, len(pad))])
        sign = np.where(np.arange(len(pad)) % 2 == 0, 1.0, -1.0)
        padded = Context(direction=np.concatenate([ctx.direction, np.repeat(sign[:, None], nj, axis=1)]),
                         payload_kg=payload)
        qq = np.concatenate([q, pad])
        obs = Observations(qq, np.zeros((len(qq), 3)), np.zeros(len(qq), int), self.target_names)
        out = []
        built: dict[str, list[Term]] = {}
        for e in self.applied:
            if e.cause not in built:
                built[e.cause] = CAUSES[e.cause].terms(self.model, self.layout, self.x, obs, padded)
            term = next((t for t in built[e.cause] if t.names == e.names), None)
            if term is None:  # several places at once: the analysis' search built it from single places
                term = _combined(e, built[e.cause], len(qq), nj)
            if term is None:
                raise ValueError(f"{e.cause} {e.where}: the cause no longer offers a term with parameters "
                                 f"{', '.join(e.names)}; this model file was written by another version")
            out.append(_rows(term, slice(0, n)))
        return out

    def _bases(self, q, ctx):
        terms = self.terms_at(q, ctx)
        theta = np.concatenate([e.theta for e in self.applied]) if terms else np.zeros(0)
        return combine_bases(tuple(terms), len(q), self.model.n_joints), theta

    def joint_delta(self, q: np.ndarray, ctx: Context | None = None) -> np.ndarray:
        """(N, nj) rad: what the joint-space effects add to the reported joint values."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        if not self.applied:
            return self._periodic_delta(q)
        bases, theta = self._bases(q, ctx)
        return bases.joint.delta(theta) + self._periodic_delta(q)

    def end_frames(self, q: np.ndarray, offset_mm: np.ndarray, ctx: Context | None = None,
                   chain: str | None = None):
        """Rotation (N, 3, 3) and position (N, 3) mm of a point fixed in the end frame, in the
        robot base frame, with every applied effect; offset_mm (3,) or (N, 3)."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        offset = np.broadcast_to(np.asarray(offset_mm, dtype=float), (len(q), 3))
        chains = np.full(len(q), chain or self.model.default_chain, dtype=object)
        return self._frames(q, offset, chains, ctx)[:2]

    def deflected_frames(self, q: np.ndarray, offset_mm: np.ndarray, ctx: Context | None = None):
        """``end_frames`` of the default chain and the joint values the rigid geometry sees (q plus
        the joint-space effects), (rot, p, q_model)."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        offset = np.broadcast_to(np.asarray(offset_mm, dtype=float), (len(q), 3))
        return self._frames(q, offset, np.full(len(q), self.model.default_chain, dtype=object), ctx)

    def _frames(self, q, offset, chains, ctx):
        bases, theta = self._bases(q, ctx) if self.applied else (None, None)
        qm = q + self._periodic_delta(q) + (0.0 if bases is None else bases.joint.delta(theta))
        rot, p = np.empty((len(q), 3, 3)), np.empty((len(q), 3))
        extra = bases is not None and (bases.param is not None or bases.cartesian is not None)
        for name in dict.fromkeys(chains):
            rows = np.flatnonzero(chains == name)
            chain = self.model.chains[name]
            if not extra:
                r, org = forward(chain, self.k, qm[rows])
                rot[rows], p[rows] = r, org + np.einsum("nij,nj->ni", r, offset[rows])
                continue
            pr, jp, _, rot[rows] = point_jacobians(chain, self.k, qm[rows], offset[rows], self.model.n_params,
                                                   self.model.n_joints)
            if bases.param is not None:  # d p / d k in the base frame: the instrument's rotation is not in it
                pr = pr + param_columns(jp, (bases.param[0], bases.param[1][rows])) @ theta
            if bases.cartesian is not None:  # term columns are in the instrument frame
                pr = pr + (bases.cartesian[rows] @ theta) @ se3.rotvec_to_matrix(self.base[3:])
            p[rows] = pr
        return rot, p, qm

    def predict(self, q: np.ndarray, target: np.ndarray, ctx: Context | None = None) -> np.ndarray:
        """Target positions in the instrument frame (N, 3) mm, as a measurement would give them."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        target = np.asarray(target, dtype=int)
        chains = np.array([self.model.chain_for(t) for t in self.target_names], dtype=object)[target]
        _, p, _ = self._frames(q, self.offsets[target], chains, ctx)
        r = se3.rotvec_to_matrix(self.base[3:])
        return p @ r.T + self.base[:3]


def _pad_rows(n_joints: int) -> np.ndarray:
    """Configurations spread over a whole turn of every joint, each joint at its own phase."""
    i = np.arange(_PAD_ROWS)[:, None]
    j = np.arange(n_joints)[None, :]
    return -np.pi + 2.0 * np.pi * ((i * (1.0 + 0.618 * j) + 0.37 * j) % _PAD_ROWS) / _PAD_ROWS


def _rows(term: Term, rows) -> Term:
    """The same term restricted to some rows of its bases."""
    return replace(term,
                   joint_basis=None if term.joint_basis is None else term.joint_basis[rows],
                   cart_basis=None if term.cart_basis is None else term.cart_basis[rows],
                   param_basis=None if not term.param_basis else {p: b[rows] for p, b in term.param_basis.items()})


def from_fit(model: KinematicModel, target_names, x: np.ndarray, terms=(), theta=(), q=None) -> CalibratedModel:
    """The calibrated model of a fit: x in the layout of ``model`` (or, with a structural term, of
    that term's model), and the non-structural terms' parameters theta in the order given.
    q: the fit's joint values (N, nj), for what a periodic error's data covered (else a whole turn)."""
    terms = tuple(terms)
    structural = [t for t in terms if t.model is not None]
    effects, col = [], 0
    kin_model = model
    for t in terms:
        if t.model is not None:
            continue
        values = np.asarray(theta[col: col + t.size], float)
        extra = _recordable(t.extra)
        if t.cause == PERIODIC and q is not None:
            extra["coverage_rad"] = {str(p.joint): [list(c) for c in p.coverage_rad]
                                     for p in fitted_errors(t, values, np.asarray(q, float))}
        effects.append(Effect(t.cause, dict(t.where), tuple(t.names), values, tuple(t.units), extra))
        col += t.size
    for t in structural:
        kin_model = t.model
        for name in t.names:
            i = kin_model.index(name)
            effects.append(Effect(t.cause, dict(t.where), (name,), np.array([x[i]]), tuple(t.units)))
    layout = Layout(kin_model, tuple(target_names))
    return CalibratedModel(kin_model, np.array(x[: layout.n_kin], float), np.array(x[layout.base], float),
                           tuple(target_names), layout.offsets(x).astype(float), tuple(effects))


def periodic_errors(effect: Effect) -> list:
    """A cyclic_joint_error entry as periodic errors per joint: a PeriodicSpline of each joint's spline
    coefficients (names k<j>_<i>, one per knot) and a PeriodicJointError of its orders (names s<j>_<n>,
    c<j>_<n>); covered angles from extra.coverage_rad (else a whole turn)."""
    coverage = effect.extra.get("coverage_rad") or {}
    coef: dict[int, dict[int, list[float]]] = {}
    knots: dict[int, list[float]] = {}
    for name, value in zip(effect.names, effect.theta):
        joint, index = (int(v) for v in name[1:].split("_"))
        if name[0] == "k":
            knots.setdefault(joint, []).append(float(value))
        else:
            coef.setdefault(joint, {}).setdefault(index, [0.0, 0.0])["sc".index(name[0])] = float(value)
    out = []
    for joint in sorted(set(coef) | set(knots)):
        cover = tuple(tuple(map(float, c)) for c in coverage.get(str(joint), [(-np.inf, np.inf)]))
        if joint in knots:
            out.append(PeriodicSpline(joint, tuple(knots[joint]), cover))
        if joint in coef:
            by_order = coef[joint]
            orders = tuple(sorted(by_order))
            out.append(PeriodicJointError(joint, orders, tuple(by_order[n][0] for n in orders),
                                          tuple(by_order[n][1] for n in orders), cover))
    return out


def _recordable(extra: dict) -> dict:
    """What of a term's extra information is plain (numbers, words, small lists and mappings of them):
    per-row arrays, spectra and the parts a term was composed of stay in memory."""
    def plain(v, depth=0):
        if isinstance(v, (bool, int, float, str, np.integer, np.floating)):
            return True
        if depth < 3 and isinstance(v, (list, tuple)) and len(v) <= 256:
            return all(plain(u, depth + 1) for u in v)
        if depth < 3 and isinstance(v, dict):
            return all(plain(u, depth + 1) for u in v.values())
        return False
    return {k: v for k, v in (extra or {}).items() if plain(v)}


def with_structural(model: KinematicModel, effects) -> KinematicModel:
    """The rigid model with every structural effect's extra parameter (a Hayati beta) added."""
    for e in effects:
        if e.cause == STRUCTURAL:
            for name in e.names:
                if name not in model.param_names:
                    model = with_hayati_beta(model, int(name.removeprefix("beta")) - 1)
    return model


def _combined(effect: Effect, offered: list[Term], n_rows: int, n_joints: int) -> Term | None:
    """The term of an effect at several places, rebuilt as the analysis' forward search builds it
    (``Cause.combine`` of single-place terms, one per place, whose parameters together are the
    effect's), or None when the cause's single places do not make it up."""
    wanted = set(effect.names)
    parts = [t for t in offered if not t.multi and set(t.names) <= wanted]
    if sorted(n for t in parts for n in t.names) != sorted(wanted) or len(parts) < 2:
        return None
    term = CAUSES[effect.cause].combine(tuple(parts), n_rows, n_joints)
    return term if term.names == effect.names else None

