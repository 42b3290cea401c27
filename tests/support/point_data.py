"""Point-form data from an arm with a hidden geometry: a socket plate at several placements.

The simulated arm (``SimulatedArm``: hidden geometric errors of up to 0.5 mm and 0.05 deg, a target
offset a few mm off its drawing) seats its target in each socket of a plate in many orientations;
each seating lands within the repeatability of the socket's centre (the tip is at c + e, e normal
with ``repeatability_mm`` per axis), and the joint values the true arm needs for that are what the
controller reports. The truth (points, arm) is returned for scoring only. ``campaign`` writes a whole
campaign (the CSV and its fixture file) for the command line and the benches.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cellcal.config.robot_files import load_robot
from cellcal.measurements.writer import write_measurements
from cellcal.sims.physics.kinematic_arm import SimulatedArm
from cellcal.solvers.geometry import se3
from cellcal.solvers.geometry.chain import forward
from cellcal.solvers.identification.measurement_model import Layout

SPACING_MM = 50.0


@dataclass
class PlateData:
    q: np.ndarray  # (N, nj)
    point: list[str]
    setup: list[str]
    true_points: dict  # (setup, point) -> position in the true base frame, mm


def plate_placements(rng, n: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """n (centre, direction hole_0 -> hole_1) spread around the robot, in reach of a UR10e's tool."""
    out = []
    for k in range(n):
        azimuth = 2 * np.pi * k / n + rng.uniform(-0.3, 0.3)
        radius = rng.uniform(550.0, 850.0)
        height = rng.uniform(-100.0, 400.0)
        centre = np.array([radius * np.cos(azimuth), radius * np.sin(azimuth), height])
        turn = rng.uniform(0, np.pi)
        out.append((centre, np.array([np.cos(turn), np.sin(turn), 0.0])))
    return out


def _solve(chain, k, offset, goal_rot, goal_pos, q0, iters=60, warp=None):
    """Joints putting the target (offset on the flange) at goal_pos with the end frame at goal_rot,
    for each row (damped Newton on central differences, all rows at once); NaN rows did not converge.
    warp: reported joints -> the joints the arm really stands at (a hidden joint-space effect)."""
    q = q0.copy()
    n, nj = q.shape
    h = 1e-6
    steps = np.concatenate([np.zeros((1, nj)), np.eye(nj) * h, -np.eye(nj) * h])
    for _ in range(iters):
        qq = (q[:, None, :] + steps[None]).reshape(-1, nj)
        rot, org = forward(chain, k, qq if warp is None else warp(qq))
        rot = rot.reshape(n, 2 * nj + 1, 3, 3)
        pos = (org + np.einsum("nij,j->ni", rot.reshape(-1, 3, 3), offset)).reshape(n, 2 * nj + 1, 3)
        err_p = goal_pos - pos[:, 0]
        err_r = se3.matrix_to_rotvec(np.einsum("nij,nkj->nik", goal_rot, rot[:, 0]))
        err = np.concatenate([err_p / 1000.0, err_r], axis=1)
        if np.abs(err).max() < 1e-11:
            break
        dp = (pos[:, 1:nj + 1] - pos[:, nj + 1:]) / (2 * h) / 1000.0
        dr = se3.matrix_to_rotvec(np.einsum("nmij,nmkj->nmik", rot[:, 1:nj + 1], rot[:, nj + 1:])
                                  .reshape(-1, 3, 3)).reshape(n, nj, 3) / (2 * h)
        jac = np.concatenate([dp, dr], axis=2).transpose(0, 2, 1)  # (n, 6, nj)
        step = np.linalg.solve(jac @ jac.transpose(0, 2, 1) + 1e-8 * np.eye(6), err[:, :, None])[:, :, 0]
        dq = np.einsum("nji,nj->ni", jac, step)
        q = q + dq / np.maximum(1.0, np.abs(dq).max(axis=1) / 0.3)[:, None]
    ok = np.abs(err).max(axis=1) < 1e-9
    q[~ok] = np.nan
    return q


WRIST_SEEDS_DEG = {"normal": [0.0, -100.0, 100.0, -90.0, -90.0, 0.0],  # a UR's usual wrist, tool down
                   "flipped": [0.0, -100.0, 100.0, 90.0, 90.0, 0.0]}  # the other wrist branch, same tool pose


def seat(arm: SimulatedArm, placements, per_socket: int, rng, setups=None, repeatability_mm=0.03,
         max_tilt_deg=35.0, stylus_radius_mm=None, wrists=("normal",), spacing_mm=SPACING_MM,
         warp=None) -> PlateData:
    """Seat the arm's target in both sockets (spacing_mm apart) of each placement, per_socket random
    orientations each, shared out over the wrist branches; with stylus_radius_mm the points are balls
    and the target touches each at a random spot of its upper half. A seat the true arm cannot reach
    on its branch within the joint limits is drawn again. warp: a hidden joint-space effect (reported
    joints -> the joints the arm really stands at), as ``_solve`` takes it."""
    model = arm.model
    layout: Layout = arm.truth.layout
    x = arm.truth.x
    k = x[: layout.n_kin]
    offset = x[layout.target(0)]
    chain = model.chains[model.default_chain]
    lim = model.joint_limits if model.joint_limits is not None else np.tile([-2 * np.pi, 2 * np.pi], (6, 1))
    qs, points, names, truth = [], [], [], {}
    for s, (centre, direction) in enumerate(placements):
        setup = setups[s] if setups else f"plate_{s}"
        for h, sign in enumerate((-0.5, 0.5)):
            c = centre + sign * spacing_mm * direction
            truth[(setup, f"hole_{h}")] = c
            got = []
            for b, wrist in enumerate(wrists):
                want = per_socket * (b + 1) // len(wrists)
                seed_q = np.deg2rad(WRIST_SEEDS_DEG[wrist])
                for _ in range(50):
                    if len(got) >= want:
                        break
                    m = 4 * per_socket
                    tilt = np.deg2rad(rng.uniform(0, max_tilt_deg, m))
                    spin, lean = rng.uniform(-np.pi, np.pi, m), rng.uniform(-np.pi, np.pi, m)
                    down = se3.rotvec_to_matrix(np.array([np.pi, 0.0, 0.0]))
                    axis = np.stack([np.cos(lean), np.sin(lean), np.zeros(m)], axis=1) * tilt[:, None]
                    goal_rot = np.einsum("nij,jk,nkl->nil", se3.rotvec_to_matrix(axis), down,
                                         se3.rotvec_to_matrix(np.stack([np.zeros(m), np.zeros(m), spin], 1)))
                    goal = c + rng.normal(scale=repeatability_mm, size=(m, 3))
                    if stylus_radius_mm is not None:
                        n = rng.normal(size=(m, 3))
                        n[:, 2] = np.abs(n[:, 2])
                        goal += stylus_radius_mm * n / np.linalg.norm(n, axis=1)[:, None]
                    q0 = np.tile(seed_q, (m, 1))
                    q0[:, 0] = np.arctan2(c[1], c[0])
                    q = _solve(chain, k, offset, goal_rot, goal, q0, warp=warp)
                    ok = np.isfinite(q).all(axis=1)
                    ok[ok] &= np.all((q[ok] >= lim[:, 0]) & (q[ok] <= lim[:, 1]), axis=1)
                    ok[ok] &= np.sign(np.sin(q[ok, 4])) == np.sign(np.sin(seed_q[4]))  # stayed on its branch
                    got.extend(q[ok][: want - len(got)])
            qs.extend(got)
            points += [f"hole_{h}"] * len(got)
            names += [setup] * len(got)
    return PlateData(np.array(qs), points, names, truth)


def write(path, data: PlateData, rows=None) -> None:
    rows = np.arange(len(data.q)) if rows is None else np.asarray(rows)
    write_measurements(path, q_rad=data.q[rows], xyz_mm=None, point=[data.point[i] for i in rows],
                       setup=[data.setup[i] for i in rows])


def fixture_text(sd_mm: float = 0.01) -> str:
    return f"points: [hole_0, hole_1]\ndistances_mm:\n  - [hole_0, hole_1, 50.0, {sd_mm}]\nseating_sd_mm: 0.03\n"


def workspace_errors(arm: SimulatedArm, k, offset, q, align_from=None, align_to=None) -> np.ndarray:
    """Distance between a calibrated arm's target (kinematics k, offset) and the true one at poses q,
    in the base frame. A calibration from fixtures or a tracker fixes the base frame only by
    convention, so the calibrated frame is first put onto the true one: by a rigid fit of
    align_from -> align_to when given (the fitted fixture points onto their true positions: the error
    relative to the plates), else by the rigid fit over the poses themselves (the gauge-free error)."""
    layout: Layout = arm.truth.layout
    model = arm.model
    chain = model.chains[model.default_chain]
    rot, org = forward(chain, arm.truth.x[: layout.n_kin], q)
    truth = org + rot @ arm.truth.x[layout.target(0)]
    rot, org = forward(chain, np.asarray(k), q)
    mine = org + rot @ np.asarray(offset)
    r, t = se3.rigid_fit(*((align_from, align_to) if align_from is not None else (mine, truth)))
    return np.linalg.norm(mine @ r.T + t - truth, axis=1)


def campaign(folder, setups: int, per_socket: int = 8, seed: int = 1, spacing_mm: float = 200.0,
             sd_mm: float = 0.01, amp_deg: float = 0.0, stylus_radius_mm=None):
    """A point-form campaign on disk: a UR10e (hidden geometry, repeatability 0.03 mm, target 100 mm off
    the flange) seated per_socket times in both sockets of a bar spacing_mm long at ``setups`` placements
    (tilt up to 45 deg, both wrist branches), with a third-order periodic error of amp_deg hidden at joint 5
    (0: none). Writes folder/points.csv and folder/fixture.yaml; returns their paths and the PlateData."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    arm = SimulatedArm(load_robot("ur10e"), rng, repeatability_mm=0.03, target_offsets=[[0.0, 0.0, 100.0]])

    def warp(q):
        q = q.copy()
        q[:, 4] += np.deg2rad(amp_deg) * np.sin(3 * q[:, 4] + 0.7)
        return q

    data = seat(arm, plate_placements(rng, setups), per_socket, rng, max_tilt_deg=45.0, wrists=("normal", "flipped"),
                spacing_mm=spacing_mm, warp=warp if amp_deg else None, stylus_radius_mm=stylus_radius_mm)
    write(folder / "points.csv", data)
    text = f"points: [hole_0, hole_1]\ndistances_mm:\n  - [hole_0, hole_1, {spacing_mm}, {sd_mm}]\nseating_sd_mm: 0.03\n"
    if stylus_radius_mm is not None:
        text += f"stylus_radius_mm: {stylus_radius_mm}\n"
    (folder / "fixture.yaml").write_text(text)
    return folder / "points.csv", folder / "fixture.yaml", data
