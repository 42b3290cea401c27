"""A simulated arm with physical effects beyond rigid geometry, each of hidden size.

Every effect of the causes vocabulary can be switched on: compliance from a
link-mass model (and payload), backlash from the approach direction, thermal
growth along a warm-up curve, cyclic joint error, tilted parallel axes, trigger
latency with jitter. Sizes are set by the TCP displacement they cause (rms over
the workspace), so a test can say "an effect three times the noise". The truth
stays inside the simulation; analysis code gets only the measured data.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cellcal.solvers.analysis.effects import CAUSES, Context, approach_directions
from cellcal.solvers.geometry.gravity import gravity_torques
from cellcal.solvers.identification.measurement_model import Observations, predict
from cellcal.solvers.geometry.robot_model import KinematicModel, with_hayati_beta
from cellcal.sims.physics.kinematic_arm import ArmTruth, SimulatedArm
from cellcal.sims.physics.workspace import full_workspace

AMBIENT_C = 21.0  # the cell's temperature: a cold arm
WARMUP_K = 8.0  # how far a thermal drift's arm warms up over a campaign (its size is reached there)
CAUSE_IDS = tuple(CAUSES)  # every cause analyze can name, and so every effect the arm can hide


@dataclass(frozen=True)
class HiddenEffect:
    cause: str
    joint: int | None = None  # 0-based; for parallel_axis_tilt the first joint of the pair
    rms_mm: float = 0.3  # TCP displacement it causes, rms over the workspace
    order: int = 1  # cyclic_joint_error: periods per turn
    phase_rad: float = 0.0
    # cyclic_joint_error with several orders: (order, relative amplitude, phase_rad) each, instead of order
    harmonics: tuple[tuple[int, float, float], ...] = ()
    tau_s: float = 1800.0  # thermal_drift: warm-up time constant
    jitter_s: float = 0.0  # trigger_latency: random part of the latency
    size: float | None = None  # the physical size itself (as hidden_size reports it) instead of rms_mm

    def __post_init__(self):
        if self.cause not in CAUSE_IDS:
            raise ValueError(f"unknown effect {self.cause!r} (known: {', '.join(CAUSE_IDS)})")


@dataclass(frozen=True)
class Campaign:
    obs: Observations
    ctx: Context
    true_joint_delta: np.ndarray  # (N, nj) joint-space part of the effects (truth, for scoring)


def default_masses(model: KinematicModel):
    """A plausible link-mass model when the file gives none: heavier long links."""
    masses, coms = [], []
    nom = dict(zip(model.param_names, model.nominal))
    for j in range(1, model.n_joints + 1):
        a, d = nom.get(f"a{j}", 0.0), nom.get(f"d{j}", 0.0)
        length_m = (abs(a) + abs(d)) / 1000.0
        masses.append(1.0 + 12.0 * length_m)
        coms.append(np.array([-a / 2.0, 0.0, -d / 2.0]) if model.convention == "dh"
                    else np.array([a / 2.0, 0.0, d / 2.0]))
    return masses, coms


class PhysicalArm(SimulatedArm):
    """SimulatedArm plus hidden physical effects."""

    def __init__(self, model: KinematicModel, rng: np.random.Generator, effects=(), **kwargs):
        self.effects = tuple(effects)
        self.nominal_model = model
        tilt = [e for e in self.effects if e.cause == "parallel_axis_tilt"]
        truth_model = model
        for e in tilt:
            truth_model = with_hayati_beta(truth_model, e.joint)
        super().__init__(truth_model, rng, **kwargs)
        self.model = model  # what the cell's owner believes
        if model.links and all(l.mass_kg is not None and l.com_mm is not None for l in model.links):
            self.masses = [l.mass_kg for l in model.links]
            self.coms = [l.com_mm for l in model.links]
        else:
            self.masses, self.coms = default_masses(model)
        self._size = {}
        reference = full_workspace(model, 200, np.random.default_rng(12345))
        for e in self.effects:
            self._size[e] = self._calibrate(e, reference, rng) if e.size is None else e.size
            if e.cause == "parallel_axis_tilt":
                x = self.truth.x.copy()
                x[self.truth.layout.model.index(f"beta{e.joint + 1}")] = self._size[e]
                self._truth = ArmTruth(self.truth.layout, x)

    # -- effects at unit size -------------------------------------------------
    def _unit_delta_q(self, e: HiddenEffect, q, direction, payload, dq):
        d = np.zeros_like(q)
        k = self.truth.x[: self.truth.layout.n_kin]
        if e.cause == "joint_compliance":
            tau = gravity_torques(self.truth.layout.model, k, q, self.masses, self.coms, payload_kg=payload)
            d[:, e.joint] = tau[:, e.joint]
        elif e.cause == "backlash":
            d[:, e.joint] = 0.5 * direction[:, e.joint]
        elif e.cause == "cyclic_joint_error":
            for n, weight, phase in e.harmonics or ((e.order, 1.0, e.phase_rad),):
                d[:, e.joint] += weight * np.sin(n * q[:, e.joint] + phase)
        elif e.cause == "trigger_latency":
            d = -dq
        return d

    def _positions(self, q, target, dT=None, k_thermal=0.0):
        layout, x = self.truth.layout, self.truth.x
        obs = Observations(q, np.zeros((len(q), 3)), target, layout.target_names)
        p = predict(layout, x, obs)
        if dT is not None and k_thermal:
            grown = x.copy()
            lengths = np.flatnonzero(~layout.model.param_is_angle)
            s = 1e-4
            grown[lengths] *= 1.0 + s
            p = p + (predict(layout, grown, obs) - p) * (k_thermal * dT / s)[:, None]
        return p

    def _calibrate(self, e: HiddenEffect, q, rng) -> float:
        """Physical size that makes the TCP move by e.rms_mm rms over the workspace."""
        target = np.zeros(len(q), dtype=int)
        base = self._positions(q, target)
        if e.cause == "parallel_axis_tilt":
            i = self.truth.layout.model.index(f"beta{e.joint + 1}")
            x = self.truth.x.copy()
            x[i] = 1e-3
            moved = predict(self.truth.layout, x, Observations(q, np.zeros((len(q), 3)), target,
                                                               self.truth.layout.target_names))
            size = 1e-3 * e.rms_mm / np.sqrt(np.mean(np.sum((moved - base) ** 2, axis=1)))
            return size * rng.choice([-1.0, 1.0])
        if e.cause == "thermal_drift":
            dT = np.ones(len(q))
            moved = self._positions(q, target, dT, 1e-4)
            return 1e-4 * e.rms_mm / np.sqrt(np.mean(np.sum((moved - base) ** 2, axis=1)))
        direction = np.where(rng.random(q.shape) < 0.5, -1.0, 1.0)
        dq = rng.normal(size=q.shape) * 0.1
        unit = self._unit_delta_q(e, q, direction, None, dq)
        moved = self._positions(q + 1e-4 * unit / max(np.abs(unit).max(), 1e-12), target)
        per = np.sqrt(np.mean(np.sum((moved - base) ** 2, axis=1))) / (1e-4 / max(np.abs(unit).max(), 1e-12))
        sign = 1.0 if e.cause in ("joint_compliance", "trigger_latency") else rng.choice([-1.0, 1.0])
        return sign * e.rms_mm / per

    def hidden_size(self, e: HiddenEffect) -> float:
        """Truth: c (rad/Nm), b (rad), A (rad), k (1/K), beta (rad) or tau (s). For scoring only."""
        return self._size[e]

    def reached(self, q, target=None, payload_kg=None, temp_c=None) -> np.ndarray:
        """Truth: where the targets really are at commanded joints q (N, 3) mm, instrument frame, with
        every joint-space effect and no noise (approach directions from the row order), the arm at rest
        (no trigger latency) and at ``temp_c`` (a thermal drift's temperature; None: at AMBIENT_C, cold).
        For scoring."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        target = np.zeros(len(q), dtype=int) if target is None else np.asarray(target)
        direction = approach_directions(q)
        payload = None if payload_kg is None else np.broadcast_to(np.asarray(payload_kg, float), (len(q),)).copy()
        delta = sum((self._size[e] * self._unit_delta_q(e, q, direction, payload, None) for e in self.effects
                     if e.cause not in ("parallel_axis_tilt", "thermal_drift", "trigger_latency")), np.zeros_like(q))
        thermal = [e for e in self.effects if e.cause == "thermal_drift"]
        if thermal and temp_c is not None:
            dT = np.broadcast_to(np.asarray(temp_c, dtype=float) - AMBIENT_C, (len(q),))
            return self._positions(q + delta, target, dT, self._size[thermal[0]] / WARMUP_K)
        return self._positions(q + delta, target)

    # -- a measurement campaign ---------------------------------------------------
    def campaign(self, q, *, target=None, payload_kg=None, t_s=None, dq_rad_s=None,
                 warmup_K: float | None = None) -> Campaign:
        """Visit q in order and measure; returns data as a CSV would carry it."""
        warmup_K = WARMUP_K if warmup_K is None else warmup_K
        q = np.atleast_2d(np.asarray(q, dtype=float))
        n = len(q)
        target = np.zeros(n, dtype=int) if target is None else np.asarray(target)
        direction = approach_directions(q)
        payload = None if payload_kg is None else np.broadcast_to(np.asarray(payload_kg, float), (n,)).copy()
        delta = np.zeros_like(q)
        dT, k_thermal, temp = None, 0.0, None
        for e in self.effects:
            if e.cause == "thermal_drift":
                t = np.arange(n) * 30.0 if t_s is None else np.asarray(t_s, dtype=float)
                t_s = t
                dT = warmup_K * (1.0 - np.exp(-(t - t.min()) / e.tau_s))
                k_thermal = self._size[e] / warmup_K  # rms_mm is reached at full warm-up
                temp = AMBIENT_C + dT
            elif e.cause == "trigger_latency":
                if dq_rad_s is None:
                    raise ValueError("trigger_latency needs the joint velocities at the triggers (dq_rad_s)")
                tau = self._size[e] + e.jitter_s * self.rng.normal(size=n)
                delta += -dq_rad_s * tau[:, None]
            elif e.cause != "parallel_axis_tilt":
                delta += self._size[e] * self._unit_delta_q(e, q, direction, payload, dq_rad_s)
        p = self._positions(q + delta, target, dT, k_thermal)
        p = p + self.rng.normal(scale=self.repeatability_mm, size=p.shape)
        p = p + self.rng.normal(size=p.shape) * self.tracker.sigma(p)[:, None]
        obs = Observations(q.copy(), p, target, self.target_names)
        ctx = Context(direction, None if t_s is None else np.asarray(t_s, float), temp, payload,
                      None if dq_rad_s is None else np.asarray(dq_rad_s, float))
        return Campaign(obs, ctx, delta)
