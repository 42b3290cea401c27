"""cyclic_joint_error: periodic transmission or encoder error, of any order.

Delta q_j = sum_n A_jn sin(n q_j + phi_jn) = sum_n a_jn sin(n q_j) + b_jn cos(n q_j). Gear
eccentricity gives n = 1, encoder mounting n = 2, and the teeth and poles of a joint's
gears and sensors give orders in the tens, different on each joint.

Search. For each joint, orders 1 .. ``order_bound`` are scanned by a periodogram of the
geometric fit's residual projected on the joint's direction of effect (d p / d q_j): the
least-squares power of each order alone. The ORDER_CANDIDATES strongest orders, picked one
at a time from what the orders before leave (``pursuit``), become single-order terms (places);
the analysis' forward search (``solvers.analysis.selection``) combines (joint, order) places, the
same search every cause with places gets. The picks are made on all rows and again on each
fold's training rows alone, so that the nested selection inside a fold chooses only among
orders that fold's training rows picked.

Order bound: an order n has a half-period of pi / n rad. Poses sampled at random put a
joint at irregular angles; the order is resolved only where consecutive sampled angles
lie closer than that, so the bound is pi over the SPACING_QUANTILE quantile of the gaps
between the joint's sorted angles (Nyquist in the spread of its angles), and at most
MAX_ORDER.

Coverage: the error function is known only where the poses put the joint. A fitted
error carries its joint's covered angle intervals (``fitted_errors``);
``PeriodicJointError.delta_rad`` is 0 outside them: the rigid model.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import numpy as np

from cellcal.solvers.estimation.crossval import NEIGHBOUR_RAD, fold_ids, training_rows
from cellcal.solvers.identification.measurement_model import jacobian_chunks
from cellcal.solvers.analysis.effects import periodic_spline
from cellcal.solvers.analysis.effects.base import Cause, JointBasis, Term

MIN_RANGE_RAD = np.deg2rad(60.0)  # a joint that barely moves shows no period
MAX_ORDER = 120  # content measured on real arms reaches ~40; the scan goes well past it
SPACING_QUANTILE = 0.9
ORDER_CANDIDATES = 6  # strongest orders per joint (on each fold's training rows) the selection chooses among
COVERAGE_GAP_RAD = np.deg2rad(10.0)  # a joint angle range no pose visited is outside the coverage


def order_bound(qj: np.ndarray) -> int:
    """Highest order this joint's sampled angles resolve (see the module docstring)."""
    angles = np.unique(np.round(np.asarray(qj, dtype=float), 6))
    if len(angles) < 4 or np.ptp(angles) < MIN_RANGE_RAD:
        return 0
    gap = float(np.quantile(np.diff(angles), SPACING_QUANTILE))
    return int(min(MAX_ORDER, np.floor(np.pi / max(gap, 1e-9) * (1.0 + 1e-4))))  # angles are rounded to 1e-6


def coverage_intervals_rad(qj: np.ndarray, max_gap_rad: float) -> list[tuple[float, float]]:
    """Angle intervals the data cover: sorted angles split where two lie more than max_gap_rad apart."""
    angles = np.sort(np.asarray(qj, dtype=float))
    cuts = np.flatnonzero(np.diff(angles) > max_gap_rad)
    starts, ends = np.r_[0, cuts + 1], np.r_[cuts, len(angles) - 1]
    return [(float(angles[a]), float(angles[b])) for a, b in zip(starts, ends)]


def harmonics(qj: np.ndarray, orders) -> np.ndarray:
    """(N, 2 k) columns sin(n q), cos(n q) for each order n."""
    nq = np.asarray(qj, dtype=float)[:, None] * np.asarray(orders, dtype=float)[None, :]
    return np.stack([np.sin(nq), np.cos(nq)], axis=2).reshape(len(qj), -1)


def _sums(q: np.ndarray, projected: np.ndarray, weight: np.ndarray, max_order: int):
    """S(n) = sum projected e^{i n q}, n = 0 .. K, and W(m) = sum weight e^{i m q}, m = 0 .. 2 K: every
    least-squares quantity of sines and cosines of orders up to K follows from these (one pass)."""
    z = np.exp(1j * np.asarray(q, dtype=float))
    s, w = np.zeros(max_order + 1, complex), np.zeros(2 * max_order + 1, complex)
    zn = np.ones_like(z)
    for m in range(2 * max_order + 1):
        w[m] = weight @ zn
        if m <= max_order:
            s[m] = projected @ zn
        zn = zn * z
    return s, w


def _power(s: np.ndarray, w: np.ndarray, max_order: int):
    """(orders 1 .. K, amplitude, power) of each order fitted alone, from ``_sums``."""
    orders = np.arange(1, max_order + 1)
    a, b = s[orders].imag, s[orders].real  # sum p sin(nq), sum p cos(nq)
    ss = 0.5 * (w[0].real - w[2 * orders].real)  # sum w sin^2
    cc = 0.5 * (w[0].real + w[2 * orders].real)
    sc = 0.5 * w[2 * orders].imag
    det = np.maximum(ss * cc - sc * sc, 1e-300)
    coef_s = (cc * a - sc * b) / det
    coef_c = (ss * b - sc * a) / det
    return orders, np.hypot(coef_s, coef_c), coef_s * a + coef_c * b


def periodogram(q: np.ndarray, projected: np.ndarray, weight: np.ndarray, max_order: int):
    """Least-squares fit of each order alone to one joint's projected residual.

    q (N,) joint angle, projected (N,) = d p / d q_j . residual (mm^2/rad), weight (N,) =
    |d p / d q_j|^2 (mm^2/rad^2). Returns (orders, amplitude (rad), power (mm^2): the drop
    of the residual sum of squares each order alone gives).
    """
    return _power(*_sums(q, projected, weight, max_order), max_order)


def pursuit(q: np.ndarray, projected: np.ndarray, weight: np.ndarray, max_order: int, count: int) -> list[int]:
    """The `count` strongest orders, one at a time: the periodogram's peak, then the peak of what is left
    once the orders picked so far are fitted together (neighbouring orders leak into each other's
    periodogram; the residual of a joint fit does not). All from ``_sums``, with
    sin(a q) e^{i n q} = (e^{i (n + a) q} - e^{i (n - a) q}) / 2i and the like: one pass over the rows."""
    return pursuit_of_sums(*_sums(q, projected, weight, max_order), max_order, count)


def pursuit_of_sums(s: np.ndarray, w: np.ndarray, max_order: int, count: int) -> list[int]:
    """``pursuit`` from the sums ``_sums`` gives (sums of disjoint rows add: a fold's training rows are
    every row less the fold's own)."""
    def wm(m):  # W(-m) = conj W(m)
        return np.where(m >= 0, w[np.abs(m)], np.conj(w[np.abs(m)]))

    n = np.arange(max_order + 1)
    picked: list[int] = []
    left = s
    for _ in range(min(count, max_order)):
        power = _power(left, w, max_order)[2]
        power[np.asarray(picked, dtype=int) - 1] = -np.inf
        picked.append(int(np.argmax(power)) + 1)
        a = np.repeat(picked, 2)
        sin = np.tile([True, False], len(picked))  # columns: sin, cos of each order picked
        plus, minus = wm(a[:, None] + a[None, :]), wm(a[:, None] - a[None, :])
        # sum w phi_k phi_l: sin sin, cos cos, and sin(a q) cos(b q) (a the row's order) and its transpose
        mixed = 0.5 * (plus.imag + minus.imag)
        gram = np.where(sin[:, None] == sin[None, :],
                        0.5 * (minus.real + np.where(sin[:, None], -plus.real, plus.real)),
                        np.where(sin[:, None], mixed, mixed.T))
        coef = np.linalg.lstsq(gram, np.where(sin, s[a].imag, s[a].real), rcond=None)[0]
        up, down = wm(n[:, None] + a[None, :]), wm(n[:, None] - a[None, :])  # sum w phi_k e^{i n q}
        left = s - np.where(sin[None, :], (up - down) / 2j, (up + down) / 2) @ coef
    return picked


@dataclass(frozen=True)
class JointSpectrum:
    """One joint's scan: what the report plots and the finding states."""

    joint: int  # 1-based
    order_bound: int
    orders: np.ndarray
    amplitude_deg: np.ndarray
    power_mm2: np.ndarray
    angle_range_deg: tuple[float, float]


@dataclass(frozen=True)
class PeriodicJointError:
    """A fitted periodic error on one joint, for use beyond the analysis (compensation)."""

    joint: int  # 1-based
    orders: tuple[int, ...]
    sin_rad: tuple[float, ...]
    cos_rad: tuple[float, ...]
    coverage_rad: tuple[tuple[float, float], ...]

    def delta_rad(self, qj: np.ndarray) -> np.ndarray:
        """The joint's error at these angles; 0 (the rigid model) outside the coverage."""
        qj = np.asarray(qj, dtype=float)
        value = harmonics(qj, self.orders) @ np.ravel(np.column_stack([self.sin_rad, self.cos_rad]))
        return np.where(periodic_spline.within(qj, self.coverage_rad), value, 0.0)

    def as_dict(self) -> dict:
        return {"joint": self.joint, "orders": list(self.orders), "sin_rad": list(self.sin_rad),
                "cos_rad": list(self.cos_rad), "amplitude_deg": [float(np.rad2deg(np.hypot(s, c)))
                                                                 for s, c in zip(self.sin_rad, self.cos_rad)],
                **periodic_spline.coverage_json(self.coverage_rad)}


def _part_key(p: Term):
    """Parts in the order of their parameters: by joint, a joint's spline before its orders."""
    return (p.where["joint"], 0 if "spline_knots" in p.where else 1, p.where.get("order", 0))


def _term(parts: tuple[Term, ...], n_rows: int, n_joints: int, spectra: dict) -> Term:
    """One term from single places (orders, and joints' splines, of any joints), with its coverage.

    ``where``: one joint: {joint, orders} and/or {spline_knots}; several: {joints, orders: [[n, ...] per
    joint], spline_knots: [K or None per joint]} (each key only when a part of that kind is in)."""
    if len(parts) == 1:
        return parts[0]
    parts = tuple(sorted(parts, key=_part_key))
    pairs = [(p.where["joint"], p.where["order"]) for p in parts if "order" in p.where]
    splines = [(p.where["joint"], p.where["spline_knots"]) for p in parts if "spline_knots" in p.where]
    joints = sorted({p.where["joint"] for p in parts})
    basis = JointBasis.side_by_side([(p.joint_basis, p.size) for p in parts], n_rows, n_joints)
    orders = [sorted(n for j2, n in pairs if j2 == j) for j in joints]
    knots = [dict(splines).get(j) for j in joints]
    if len(joints) == 1:
        where = {"joint": joints[0], **({"orders": orders[0]} if pairs else {}),
                 **({"spline_knots": knots[0]} if splines else {})}
    else:
        where = {"joints": joints, **({"orders": orders} if pairs else {}),
                 **({"spline_knots": knots} if splines else {})}
    return Term(CyclicJointError.id, where, tuple(n for p in parts for n in p.names), joint_basis=basis,
                units=tuple(u for p in parts for u in p.units), multi=len(joints) > 1,
                extra={"parts": parts, "harmonics": tuple(pairs), "splines": tuple(splines), "spectra": spectra})


class CyclicJointError(Cause):
    id = "cyclic_joint_error"

    def terms(self, model, layout, x, obs, ctx):
        """The strongest orders of every joint that moves enough, one term each, and its spline at each knot count
        and penalty weight (``periodic_spline``); the orders picked, and each count offered or not, on every row
        and again on each fold's training rows alone (the analysis' nested selection chooses among a fold's own picks:
        ``extra["all"]``, ``extra["folds"]``)."""
        nj = model.n_joints
        bounds = [order_bound(obs.q[:, j]) for j in range(nj)]
        joints = [j for j in range(nj) if bounds[j] > 0]
        if not joints:
            return []
        projected, weight = np.zeros((len(obs), nj)), np.zeros((len(obs), nj))
        for rows, p, _, jq in jacobian_chunks(layout, x, obs, with_joints=True):
            residual = p - obs.xyz_mm[rows]
            projected[rows] = np.einsum("nij,ni->nj", jq, residual)
            weight[rows] = np.einsum("nij,nij->nj", jq, jq)
        out, spectra = [], {}
        folds = ctx.folds if ctx.folds is not None else fold_ids(obs.q, 5, 0, NEIGHBOUR_RAD)
        every = np.arange(len(obs))
        left_out = [np.setdiff1d(every, training_rows(folds, k)) for k in range(len(np.unique(np.asarray(folds))))]
        for j in range(nj):
            if j not in joints:
                continue
            qj = obs.q[:, j]
            orders, amplitude, power = periodogram(qj, projected[:, j], weight[:, j], bounds[j])
            spectra[j + 1] = JointSpectrum(j + 1, bounds[j], orders, np.rad2deg(amplitude), power,
                                           (float(np.rad2deg(qj.min())), float(np.rad2deg(qj.max()))))
            total = _sums(qj, projected[:, j], weight[:, j], bounds[j])
            picked = pursuit_of_sums(*total, bounds[j], ORDER_CANDIDATES)
            by_fold = []
            for rows in left_out:  # each fold's training: every row less the fold's own (and its gap)
                s, w = _sums(qj[rows], projected[rows, j], weight[rows, j], bounds[j])
                by_fold.append(pursuit_of_sums(total[0] - s, total[1] - w, bounds[j], ORDER_CANDIDATES))
            for n in dict.fromkeys(picked + [n for p in by_fold for n in p]):
                basis = JointBasis.of_angle(qj, partial(harmonics, orders=[n]), j, nj, 2)
                out.append(Term(self.id, {"joint": j + 1, "order": int(n)}, (f"s{j + 1}_{n}", f"c{j + 1}_{n}"),
                                joint_basis=basis, units=("rad", "rad"),
                                extra={"part": True, "all": n in picked,
                                       "folds": frozenset(k for k, p in enumerate(by_fold) if n in p)}))
            # the same cause as a smooth function of the angle, not a few sinusoids: the finest spline the
            # angles resolve and coarser ones, each at every penalty weight (periodic_spline)
            for knots in periodic_spline.knot_counts(bounds[j]):
                # each count offered where it lowers the joint's own held-out residual, at each weight: one slot
                # for the joint; a count's weights share its columns
                offered, inside = periodic_spline.screen_nested(qj, projected[:, j], weight[:, j], folds, knots)
                if not offered and not inside:
                    continue
                basis = JointBasis.of_angle(qj, partial(periodic_spline.basis, knots=knots), j, nj, knots)
                names = tuple(f"k{j + 1}_{i}" for i in range(knots))
                first, rough = None, periodic_spline.roughness(knots)
                for lam in periodic_spline.SMOOTHING:
                    spline = Term(self.id, {"joint": j + 1, "spline_knots": knots}, names, joint_basis=basis,
                                  units=("rad",) * knots,
                                  extra={"spline": True, "slot": ("spline", j + 1), "penalty_weight": lam,
                                         "roughness": rough, "all": offered, "folds": inside,
                                         **({"columns_of": first} if first is not None else {})})
                    first = first or spline
                    out.append(spline)
        for t in out:
            t.extra["spectra"] = spectra
        return out

    def search_places(self, terms):
        """Each (joint, order) combines with any other; a joint's spline is a richer place: the search
        also grows a combination that may hold splines (at several joints, and orders beside them) and
        takes it when it beats the orders' by the search's GAIN (``selection.forward``). A joint's splines
        at its different knot counts and penalty weights are alternatives (one ``slot``): a combination holds one
        of them at most.

        A joint's spline once stood alone, never combined. On a measured UR10 (tracker, 1 495 and 11 911
        poses) the search's fold scores showed what that cost: the best spline (joint 2) left 0.344 and
        0.332 mm held-out rms of 0.446 and 0.441 with geometry alone, the splines of every moving joint
        together 0.223 and 0.177 in the same folds, while the (joint, order) combination, each order a
        few percent, stopped at 0.420 and 0.357. A real joint's error is neither one sinusoid nor
        confined to one joint; simulated ones of a few orders are found by the orders alone."""
        if not terms:
            return None
        return [t for t in terms if not t.extra.get("spline")], [t for t in terms if t.extra.get("spline")]

    def combine(self, parts, n_rows, n_joints):
        return _term(tuple(parts), n_rows, n_joints, parts[0].extra["spectra"])

    def details(self, term, theta, q):
        return {"errors": [e.as_dict() for e in fitted_errors(term, theta, q)], "outside_coverage": OUTSIDE_COVERAGE}

    def magnitude(self, term, theta, joint_delta):
        if term.extra.get("spline"):
            moved = np.rad2deg(joint_delta[:, term.where["joint"] - 1])
            moved = moved - moved.mean()  # a constant part is the joint's offset, which the geometry has
            return {"effective_dof": len(theta), "rms_deg": float(np.sqrt(np.mean(moved**2))),
                    "peak_to_peak_deg": float(np.ptp(moved))}
        if "harmonics" not in term.extra:
            a, b = theta
            return {"amplitude_deg": float(np.rad2deg(np.hypot(a, b))), "order": term.where["order"],
                    "phase_deg": float(np.rad2deg(np.arctan2(b, a)))}
        out, col = {}, 0
        for j, part in _layout(term):
            values = theta[col: col + part]
            col += part
            if isinstance(j, tuple):  # (joint, order): sin and cos
                out[f"joint{j[0]}_order{j[1]}_amplitude_deg"] = float(np.rad2deg(np.hypot(*values)))
                continue
            moved = np.rad2deg(_spline_delta(term, j, values))
            moved = moved - moved.mean()
            out[f"joint{j}_spline_rms_deg"] = float(np.sqrt(np.mean(moved**2)))
            out[f"joint{j}_spline_peak_to_peak_deg"] = float(np.ptp(moved))
        return out


OUTSIDE_COVERAGE = ("outside its joint's coverage the periodic error is not applied: predictions there "
                    "fall back to the rigid model")
BOUND_RULE = (f"orders 1 up to pi over the {SPACING_QUANTILE:.0%} quantile of the gaps between the joint's "
              f"sampled angles (Nyquist in their spread), at most {MAX_ORDER}")


def order_search(spectra: dict) -> dict:
    """What was scanned, per joint (1-based, as text keys): the order bound and the angles sampled."""
    return {"rule": BOUND_RULE,
            "joints": {str(j): {"orders": [1, s.order_bound], "angle_range_deg": list(s.angle_range_deg)}
                       for j, s in sorted(spectra.items())}}


def _layout(term: Term) -> list:
    """A combined term's parameters in order: ((joint, order), 2) for an order's sin and cos, (joint, K)
    for a joint's spline of K knots (``_term``'s order, read off the parameter names)."""
    out = []
    for name in term.names:
        joint, index = (int(v) for v in name[1:].split("_"))
        if name[0] == "k":
            if index == 0:
                out.append((joint, 0))
            out[-1] = (joint, out[-1][1] + 1)
        elif name[0] == "s":
            out.append(((joint, index), 2))
    return out


def _spline_delta(term: Term, joint: int, coef: np.ndarray) -> np.ndarray:
    """A combined term's spline part of `joint` at the rows of its basis (rad)."""
    part = next(p for p in term.extra["parts"] if p.where.get("spline_knots") and p.where["joint"] == joint)
    return part.joint_basis.delta(coef)[:, joint - 1]


def fitted_errors(term: Term, theta: np.ndarray, q: np.ndarray) -> list:
    """The fitted term as one periodic error per joint (``PeriodicJointError`` or
    ``periodic_spline.PeriodicSpline``), each with the angles the data cover (split where the poses
    left the joint out over more than COVERAGE_GAP_RAD)."""
    if term.extra.get("spline"):
        j = term.where["joint"]
        return [periodic_spline.PeriodicSpline(j, tuple(float(c) for c in theta),
                                               tuple(coverage_intervals_rad(q[:, j - 1], COVERAGE_GAP_RAD)))]
    if "harmonics" not in term.extra:
        layout = [((term.where["joint"], term.where["order"]), 2)]
    else:
        layout = _layout(term)
    splines, pairs, coef, col = [], [], [], 0
    for j, part in layout:
        values = np.asarray(theta[col: col + part], dtype=float)
        col += part
        if isinstance(j, tuple):
            pairs.append(j)
            coef.append(values)
        else:
            splines.append((j, values))
    out = []
    for j in sorted({j for j, _ in splines} | {j for j, _ in pairs}):
        cover = tuple(coverage_intervals_rad(q[:, j - 1], COVERAGE_GAP_RAD))
        out += [periodic_spline.PeriodicSpline(j, tuple(float(c) for c in v), cover) for j2, v in splines if j2 == j]
        mine = [i for i, (j2, _) in enumerate(pairs) if j2 == j]
        if mine:
            out.append(PeriodicJointError(j, tuple(int(pairs[i][1]) for i in mine),
                                          tuple(float(coef[i][0]) for i in mine),
                                          tuple(float(coef[i][1]) for i in mine), cover))
    return out
