"""How large each effect typically gets on arms of a class: every candidate's fitted size judged.

A candidate that explains the data only with a size no arm of its class shows (a joint
deflecting by degrees under gravity, a gear error of a degree) is a reason against that
explanation, whatever its held-out score: the fit has found a shape in the data, not the
cause. The analysis judges every scored candidate by the size its linearised fit gives
(``linearised_size``: the Gauss-Newton step from the geometric fit on all rows, sized by the
cause's own ``magnitude``) against the typical maximum for the robot's class
(``TYPICAL_MAX``). A lead built on an implausible size does not name its cause when an
explanation of plausible size comes within the naming margin of it: the plausible contenders
compete (``naming.name_cause``).

Robot classes (``robot_class``) follow the payload, which the robot file does not give; it is
read from what the file does give:

- with every link's mass, the arm's own mass: arms rated up to 16 kg weigh up to about 150 kg
  (collaborative arms 2-4 kg per kg of payload, small industrial arms about 10), heavy arms
  (100 kg payload and more) about 1000 kg and more;
- else the reach (the farthest any chain's end gets from the vertical through the base origin
  over the joint ranges): collaborative arms of up to 16 kg reach at most about 1.5 m; medium and
  heavy arms both reach 2-3.5 m, so only a reach beyond 3.5 m says heavy;
- between these, and whenever neither says, the default class: ``DEFAULT_CLASS``.

The numbers, each with its reasoning (docs/causes.md carries the same table):

- joint_compliance, rms over the poses of a joint's deflection under gravity (deg).
  Strain-wave gears with joint torque sensors have joint stiffness of 1e4..5e4 N m/rad
  against shoulder gravity torques up to about 150 N m (Albu-Schaeffer, Haddadin, Ott et al.,
  "The DLR lightweight robot: design and control concepts for robots in human environments";
  typical of datasheets of strain-wave gears): up to about 0.5 deg. Cycloid (RV) gears of
  medium arms: 1e5..5e6 N m/rad against up to a few kN m, a tenth of a degree typical, 0.3
  an extreme (typical of datasheets of cycloid reducers; Dumas, Caro, Garnier, Furet,
  "Joint stiffness identification of six-revolute industrial serial robots"). Heavy arms:
  up to 15 kN m at the shoulder against 1e6..1e7 N m/rad, 0.5 an extreme.
- cyclic_joint_error, amplitude of one periodic term (deg; a periodic spline's rms times
  sqrt 2): the transmission error of strain-wave and cycloid gears is specified at an arc
  minute (0.017 deg) or two, encoder eccentricity below that (typical of datasheets of
  strain-wave gears and cycloid reducers); 0.1 deg an extreme for every class.
- backlash (deg): strain-wave gears have none to speak of (lost motion below an arc
  minute), 0.05 an extreme; cycloid reducers' lost motion is an arc minute new, a worn
  joint a few: 0.1 an extreme (typical of datasheets of both).
- thermal_drift, expansion coefficient (ppm/K): steel 12, aluminium 23; 30 with the
  mount's share, for every class (a material property).
- parallel_axis_tilt (deg): machined bores are parallel to a few hundredths of a degree;
  0.5 an extreme even for cast housings, every class.
- trigger_latency (ms): sensor and IO latency, below 100 ms on any controller.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from cellcal.solvers.geometry.chain import forward
from cellcal.solvers.analysis.effects import CAUSES
from cellcal.solvers.analysis.effects.base import penalised_parts
from cellcal.solvers.analysis.linearised_scorer import search_step

CLASSES = {
    "collaborative": "collaborative and other light arms, rated payload up to 16 kg",
    "medium": "medium industrial arms, rated payload 16-100 kg",
    "heavy": "heavy industrial arms, rated payload 100 kg and more",
}
DEFAULT_CLASS = "medium"  # the robot file says too little: medium arms are the most common in calibration cells
LIGHT_ARM_KG, HEAVY_ARM_KG = 150.0, 1000.0  # the arm's own mass, links summed
LIGHT_REACH_MM, HEAVY_REACH_MM = 1500.0, 3500.0
# A lead of implausible size that no explanation of plausible size comes close to (within the naming margin):
# False, it competes all the same, its size said in the grounds (the data show an effect only it explains; a
# robot file that misleads the class, or a simulation, can make it so); True, it names nothing (an effect of
# undecided cause). The default of ``AnalyzeOptions.strict_sizes``; `cellcal analyze --strict-sizes` sets it
STRICT = False


@dataclass(frozen=True)
class Quantity:
    """What is judged of a cause's size: the magnitude keys ending in each suffix (times its factor, to the
    quantity's own scale), the largest of them; its unit and what it is."""

    suffixes: dict  # key suffix -> factor
    unit: str
    what: str


QUANTITY = {
    "joint_compliance": Quantity({"deflection_rms_deg": 1.0}, "deg", "joint deflection under gravity (rms)"),
    "cyclic_joint_error": Quantity({"amplitude_deg": 1.0, "spline_rms_deg": np.sqrt(2.0)}, "deg",
                                   "gear or encoder cyclic error (amplitude)"),
    "backlash": Quantity({"backlash_deg": 1.0}, "deg", "lost motion of an assembled joint"),
    "thermal_drift": Quantity({"expansion_ppm_per_K": 1.0}, "ppm/K", "thermal expansion of steel or aluminium"),
    "parallel_axis_tilt": Quantity({"tilt_deg": 1.0}, "deg", "tilt between machined parallel axes"),
    "trigger_latency": Quantity({"latency_ms": 1.0}, "ms", "sensor and IO latency"),
}

# cause -> class -> typical maximum, in the Quantity's unit (reasoning in the module's docstring)
TYPICAL_MAX = {
    "joint_compliance": {"collaborative": 0.5, "medium": 0.3, "heavy": 0.5},
    "cyclic_joint_error": {"collaborative": 0.1, "medium": 0.1, "heavy": 0.1},
    "backlash": {"collaborative": 0.05, "medium": 0.1, "heavy": 0.1},
    "thermal_drift": {"collaborative": 30.0, "medium": 30.0, "heavy": 30.0},
    "parallel_axis_tilt": {"collaborative": 0.5, "medium": 0.5, "heavy": 0.5},
    "trigger_latency": {"collaborative": 100.0, "medium": 100.0, "heavy": 100.0},
}


@dataclass(frozen=True)
class RobotClass:
    name: str  # a key of CLASSES
    reason: str  # what in the robot file decided it

    def json(self) -> dict:
        return {"name": self.name, "meaning": CLASSES[self.name], "reason": self.reason}


@dataclass(frozen=True)
class Judgement:
    """A candidate's size against its class's typical maximum."""

    key: str  # the magnitude key judged
    value: float  # in the quantity's unit
    limit: float
    robot_class: str
    cause: str

    @property
    def plausible(self) -> bool:
        return bool(self.value <= self.limit)

    def text(self) -> str:
        q = QUANTITY[self.cause]
        verdict = "within" if self.plausible else "beyond"
        return (f"needs {self.key} {self.value:.3g}, {verdict} the {self.limit:g} {q.unit} typical of "
                f"{q.what} on {self.robot_class} arms")

    def json(self) -> dict:
        return {"key": self.key, "value": self.value, "typical_max": self.limit, "unit": QUANTITY[self.cause].unit,
                "robot_class": self.robot_class, "plausible": self.plausible}


def robot_class(model) -> RobotClass:
    """The class of the robot from its file: the arm's mass when every link's is given, else its reach."""
    masses = [link.mass_kg for link in model.links]
    if masses and len(masses) == model.n_joints and all(m is not None for m in masses):
        total = float(sum(masses))
        name = ("collaborative" if total <= LIGHT_ARM_KG else "heavy" if total >= HEAVY_ARM_KG else "medium")
        return RobotClass(name, f"link masses sum to {total:.0f} kg")
    reach = reach_mm(model)
    if reach <= LIGHT_REACH_MM:
        return RobotClass("collaborative", f"reach {reach:.0f} mm, no link masses")
    if reach >= HEAVY_REACH_MM:
        return RobotClass("heavy", f"reach {reach:.0f} mm, no link masses")
    return RobotClass(DEFAULT_CLASS, f"reach {reach:.0f} mm and no link masses: the default class")


def reach_mm(model, samples: int = 256) -> float:
    """The farthest any chain's end gets from the vertical through the base origin (as datasheets give
    reach), over joint values drawn within the joint ranges (all around where the file gives none)."""
    rng = np.random.default_rng(0)
    limits = model.joint_limits if model.joint_limits is not None else np.tile([-np.pi, np.pi], (model.n_joints, 1))
    lo, hi = np.asarray(limits, dtype=float).T
    q = rng.uniform(lo, hi, size=(samples, model.n_joints))
    up = -np.asarray(model.gravity, dtype=float) / np.linalg.norm(model.gravity)
    out = 0.0
    for chain in model.chains.values():
        end = forward(chain, model.nominal, q)[1].reshape(-1, 3)
        out = max(out, float(np.linalg.norm(end - np.outer(end @ up, up), axis=1).max()))
    return out


def judge(cause: str, size: dict, klass: str = DEFAULT_CLASS) -> Judgement | None:
    """The largest size of the cause's judged quantity against the class's typical maximum; None when the
    size has none of its keys (a tree's lumped coefficients, a time constant)."""
    q = QUANTITY.get(cause)
    if q is None:
        return None
    values = [(k, abs(float(v)) * f) for k, v in size.items() for s, f in q.suffixes.items()
              if k.endswith(s) and isinstance(v, (int, float)) and np.isfinite(v)]
    if not values:
        return None
    key, value = max(values, key=lambda kv: kv[1])
    return Judgement(key, value, TYPICAL_MAX[cause][klass], klass, cause)


def linearised_size(scorer, term, stacked=None) -> dict:
    """The term's ``magnitude`` as its linearised fit on all rows gives it (the Gauss-Newton step from
    the geometric fit, with the parameters the data separate from the geometry); for several joints of
    a joint-space cause, each joint's rms displacement too (``jointJ_deflection_rms_deg``). Costs one
    least-squares solve on the scorer's fold factors (stacked: the list of those, when already made)."""
    cols = scorer.estimated((term,))
    factors = scorer.factors.factors if stacked is None else stacked
    # the R factors of [J | r] of the folds, one under the other: the same normal equations as all rows
    a, b = np.vstack([f[:, cols] for f in factors]), np.concatenate([f[:, scorer.n_columns] for f in factors])
    if penalised_parts((term,)):  # with its own ridge (a spline's), as every fit of it is made
        normal = a.T @ a
        coef = -search_step(normal, a.T @ b, scorer.penalty((term,), cols, np.diagonal(normal)))
    else:
        coef = np.linalg.lstsq(a, b, rcond=None)[0]
    theta = np.zeros(term.size)
    theta[scorer.term_estimated(term)] = -coef[scorer.n_geometry:]
    delta = term.joint_basis.delta(theta) if term.joint_basis is not None else None
    size = dict(CAUSES[term.cause].magnitude(term, theta, delta))
    if term.cause == "joint_compliance" and delta is not None and "joints" in term.where:
        for j in term.where["joints"]:
            size[f"joint{j}_deflection_rms_deg"] = float(np.rad2deg(np.sqrt(np.mean(delta[:, j - 1] ** 2))))
    if term.extra.get("spline") and "rms_deg" in size:
        size["spline_rms_deg"] = size["rms_deg"]
    return size


def judge_candidates(candidates, scorer, klass: str) -> list:
    """Every candidate with its judgement (``Scored.judged``; None where its size has nothing to judge: a
    tree's lumped coefficients, several terms at once)."""
    stacked, out = None, []
    for c in candidates:
        judged = None
        term = c.terms[0] if len(c.terms) == 1 else None
        if term is not None and c.cause in QUANTITY and not term.param_basis:
            stacked = scorer.factors.factors if stacked is None else stacked
            judged = judge(c.cause, linearised_size(scorer, term, stacked), klass)
        out.append(dataclasses.replace(c, judged=judged))
    return out
