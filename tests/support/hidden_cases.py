"""Data sets with a hidden physical effect of a stated visibility, for tests and benches.

"An effect three times the noise" is measured where it matters: what the effect
leaves behind after a geometric calibration has absorbed all it can (the rms
residual of a rigid fit to noise-free data with the effect on), against the rms
measurement noise per point. Every effect is linear in its size, so one probe
fixes the size that gives the visibility asked for.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cellcal.solvers.identification.identify import IdentifyOptions, identify
from cellcal.solvers.identification.measurement_model import Layout, Observations, jacobian
from cellcal.solvers.geometry.robot_model import KinematicModel
from cellcal.sims.physics.kinematic_arm import TrackerNoise
from cellcal.sims.physics.physical_arm import Campaign, HiddenEffect, PhysicalArm
from cellcal.sims.physics.workspace import full_workspace, joint_sweeps

BASE_REPEATABILITY_MM = 0.05


@dataclass(frozen=True)
class HiddenCase:
    arm: PhysicalArm
    campaign: Campaign
    effects: tuple[HiddenEffect, ...]  # with their true sizes
    noise_mm: float  # rms measurement noise per point (3-D)
    noise_mean_mm: float  # mean length of the measurement noise vector: the floor of a mean error
    visible_mm: tuple[float, ...]  # per effect: rms left after a rigid calibration


def sweep_velocities(model: KinematicModel, q: np.ndarray, rng: np.random.Generator,
                     speeds_mm_s=(20.0, 40.0, 100.0)) -> np.ndarray:
    """Joint velocities of sweeps through a trigger: random direction, TCP speed from the list."""
    layout = Layout(model, ("tcp",))
    obs = Observations(q, np.zeros((len(q), 3)), np.zeros(len(q), dtype=int), ("tcp",))
    _, _, jq = jacobian(layout, layout.initial(), obs, with_joints=True)
    dq = rng.normal(size=q.shape)
    tcp = np.linalg.norm(np.einsum("nij,nj->ni", jq, dq), axis=1)
    speed = rng.choice(speeds_mm_s, size=len(q)) * rng.choice([-1.0, 1.0], size=len(q))
    return dq * (speed / np.maximum(tcp, 1e-9))[:, None]


def _arm(model, seed, effects, noise_scale, noise_free=False):
    rng = np.random.default_rng(seed)
    kwargs = dict(repeatability_mm=0.0, tracker=TrackerNoise(0.0, 0.0)) if noise_free else \
        dict(repeatability_mm=BASE_REPEATABILITY_MM * noise_scale,
             tracker=TrackerNoise(0.015 * noise_scale, 0.006 * noise_scale))
    return PhysicalArm(model, rng, effects, **kwargs)


def _visible(model, arm, q, extras) -> float:
    run = arm.campaign(q, **extras)
    fit = identify(model, run.obs, IdentifyOptions(regularize="none", prior_mm=1e9))
    return float(np.sqrt(np.mean(np.sum(fit.residuals_mm**2, axis=1))))


def make_case(model: KinematicModel, effects, visibility, *, n: int, noise_scale: float = 1.0,
              seed: int = 0) -> HiddenCase:
    """A campaign of n random poses with each effect visible at `visibility` x the noise.

    effects: HiddenEffect templates (their rms_mm is ignored); visibility: one factor per effect.
    """
    effects = tuple(effects)
    q_rng = np.random.default_rng(seed + 7919)
    q = full_workspace(model, n, q_rng)
    extras = {}
    if any(e.cause == "trigger_latency" for e in effects):
        extras["dq_rad_s"] = sweep_velocities(model, q, q_rng)
    noise_arm = _arm(model, seed, (), noise_scale)
    pure = noise_arm.campaign(q, **extras)
    noise_vec = np.linalg.norm(pure.obs.xyz_mm - noise_arm.true_positions(q, pure.obs.target), axis=1)
    noise = float(np.sqrt(np.mean(noise_vec**2)))
    sized = []
    for e, k in zip(effects, visibility):
        probe = _arm(model, seed, (e.__class__(**{**e.__dict__, "rms_mm": 1.0, "size": None}),), noise_scale,
                     noise_free=True)
        unit = probe.hidden_size(probe.effects[0])
        seen = _visible(model, probe, q, extras)
        sized.append(HiddenEffect(**{**e.__dict__, "size": unit * k * noise / seen}))
    arm = _arm(model, seed, sized, noise_scale)
    visible = tuple(_visible(model, _arm(model, seed, (e,), noise_scale, noise_free=True), q, extras)
                    for e in sized)
    return HiddenCase(arm, arm.campaign(q, **extras), tuple(sized), noise, float(noise_vec.mean()), visible)


# A heavy arm measured one joint at a time, the shoulder only a little (as a tracker campaign
# around the arm's home often is): the gravity torque on the elbow is a first harmonic of its
# own sweep angle, so compliance and a first-order cyclic error of the elbow fit alike.
SWEEP_ROBOT = "abb-irb4600"
SWEEP_SPAN_DEG = (170.0, 30.0, 170.0, 170.0, 170.0, 170.0)
SWEEP_STEPS = 12


def sweep_case(model: KinematicModel, cause: str, seed: int, joint: int = 2, rms_mm: float = 0.3):
    """(arm, configurations) of a one-joint-at-a-time campaign with `cause` hidden at `joint`
    (0-based), first order, phase drawn from the seed; measure with arm.campaign(q)."""
    rng = np.random.default_rng(seed)
    effect = HiddenEffect(cause, joint, rms_mm=rms_mm, order=1, phase_rad=float(rng.uniform(0, 2 * np.pi)))
    return _arm(model, seed, (effect,), 1.0), joint_sweeps(model, SWEEP_STEPS, SWEEP_SPAN_DEG)


def elbow_pair(tied) -> bool:
    """Is a tie (the JSON entries of ``indistinguishable``) compliance of the elbow and a cyclic
    error of it with order 1 among its orders?"""
    by_cause = {t["cause"]: t["where"] for t in tied}
    cyclic = by_cause.get("cyclic_joint_error", {})
    return (len(tied) == 2 and by_cause.get("joint_compliance") == {"joint": 3} and cyclic.get("joint") == 3
            and 1 in cyclic.get("orders", [cyclic.get("order")]))
