"""A simulated arm with a hidden true geometry, measured by a simulated tracker.

The truth (geometric errors, instrument -> base transform, target offsets) lives
in ``SimulatedArm.truth``. Tests and the demo's report may read it to score a
result; solvers never see it: they get only joint values and measured points.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cellcal.solvers.identification.measurement_model import Layout, Observations, predict
from cellcal.solvers.geometry.robot_model import KinematicModel


@dataclass(frozen=True)
class ArmTruth:
    layout: Layout
    x: np.ndarray  # true full unknown vector (kinematics, base, target offsets)

    def positions(self, q: np.ndarray, target: np.ndarray) -> np.ndarray:
        obs = Observations(q, np.zeros((len(q), 3)), target, self.layout.target_names)
        return predict(self.layout, self.x, obs)


@dataclass(frozen=True)
class TrackerNoise:
    """Laser tracker noise: standard deviation per axis = a + b * distance.

    AT960, as Cao et al. state it ("A Novel Kinematic Calibration Method for Industrial
    Robots Based on the Improved Grey Wolf Optimization Algorithm", Actuators 2025):
    15 um + 6 um/m, taken here as one standard deviation per axis, which is on the
    pessimistic side of the maker's MPE figure.
    """

    constant_mm: float = 0.015
    per_m_mm: float = 0.006

    def sigma(self, points_mm: np.ndarray) -> np.ndarray:
        return self.constant_mm + self.per_m_mm * np.linalg.norm(points_mm, axis=1) / 1000.0


class SimulatedArm:
    """Robot + tracker: returns noisy measured target positions for joint values."""

    def __init__(self, model: KinematicModel, rng: np.random.Generator, *,
                 target_names=("tcp",), length_error_mm=0.5, angle_error_deg=0.05,
                 repeatability_mm=0.05, tracker: TrackerNoise = TrackerNoise(),
                 base_distance_mm=3000.0, target_offset_mm=150.0, target_offsets=None,
                 target_offset_error_mm=2.0):
        layout = Layout(model, tuple(target_names))
        x = layout.initial()
        n = model.n_params
        err = np.where(model.param_is_angle, np.deg2rad(angle_error_deg), length_error_mm)
        x[:n] += rng.uniform(-1.0, 1.0, n) * err
        # tracker somewhere in front of the robot, looking roughly at it
        direction = rng.normal(size=3)
        direction[2] = abs(direction[2]) * 0.2
        direction /= np.linalg.norm(direction)
        x[layout.base] = np.concatenate([-direction * base_distance_mm, rng.uniform(-np.pi, np.pi, 3)])
        for i in range(len(target_names)):
            if target_offsets is None:  # a target somewhere on the tool
                x[layout.target(i)] = rng.normal(size=3) * target_offset_mm / np.sqrt(3)
            else:  # a target at a drawn position, off from its nominal by a few mm
                x[layout.target(i)] = np.asarray(target_offsets[i], dtype=float) + rng.uniform(
                    -target_offset_error_mm, target_offset_error_mm, 3)
        self._truth = ArmTruth(layout, x)
        self.model = model
        self.rng = rng
        self.repeatability_mm = repeatability_mm
        self.tracker = tracker

    @property
    def truth(self) -> ArmTruth:
        """Hidden truth: for scoring results, never an input of a solver."""
        return self._truth

    @property
    def target_names(self) -> tuple[str, ...]:
        return self._truth.layout.target_names

    def true_positions(self, q: np.ndarray, target: np.ndarray) -> np.ndarray:
        return self._truth.positions(q, target)

    def measure(self, q: np.ndarray, target=None) -> Observations:
        """Move to each configuration and measure every requested target."""
        q = np.atleast_2d(q)
        target = np.zeros(len(q), dtype=int) if target is None else np.asarray(target)
        p = self.true_positions(q, target)
        p = p + self.rng.normal(scale=self.repeatability_mm, size=p.shape)
        p = p + self.rng.normal(size=p.shape) * self.tracker.sigma(p)[:, None]
        return Observations(q.copy(), p, target, self.target_names)

    def oracle_errors(self, obs: Observations) -> np.ndarray:
        """Error of the true model on measured data: the floor any model can reach."""
        return np.linalg.norm(self.true_positions(obs.q, obs.target) - obs.xyz_mm, axis=1)
