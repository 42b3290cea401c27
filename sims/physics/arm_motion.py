"""The moving arm of every simulated cell (the fake UR controller's and the in-process
one): kinematics in metres and the motions URScript runs.

Geometry comes from our own robot model files (the same forward kinematics the solvers
use, nominal parameters, mm inside), converted to metres at this boundary because the
controller speaks SI. Motions advance one controller cycle at a time:

* ``JointMove``: movej, every joint on a synchronised trapezoidal profile, ending exactly
  on the target joints;
* ``LinearMove``: movel, TCP on a straight line (orientation by constant-axis rotation)
  with a damped-least-squares IK step per cycle, ending with an IK solved to 1e-12 m;
* ``SpeedLinear``: speedl, a TCP twist ramped up at the given acceleration;
* ``StopMotion``: stopj/stopl, the current joint velocity decelerated to rest.
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np

from cellcal.solvers.geometry.chain import forward
from cellcal.solvers.geometry.robot_model import KinematicModel

# a pure rotation counts as the path of a point this far from the axis (movel timing)
ROTATION_RADIUS_M = 0.1


class MotionFault(RuntimeError):
    """A motion the controller cannot execute (no IK solution, singularity)."""


# log_so3/exp_so3 repeat solvers.geometry.se3.matrix_to_rotvec/rotvec_to_matrix for one rotation in
# plain floats: they run several times per 2 ms cycle, and measured here they take 2.3 and
# 4.1 us against 66 and 30 us for the vectorised scipy-backed versions (15-28x faster).
def log_so3(rotation: np.ndarray) -> np.ndarray:
    """Rotation vector (angle <= pi) of a rotation matrix, via Shepperd's quaternion:
    stable at every angle, including the pi of UR's home pose."""
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = rotation.tolist()
    trace = r00 + r11 + r22
    biggest = max(trace, r00, r11, r22)
    if biggest == trace:
        w = math.sqrt(max(1.0 + trace, 0.0)) / 2.0
        x, y, z = (r21 - r12) / (4 * w), (r02 - r20) / (4 * w), (r10 - r01) / (4 * w)
    elif biggest == r00:
        x = math.sqrt(max(1.0 + r00 - r11 - r22, 0.0)) / 2.0
        w, y, z = (r21 - r12) / (4 * x), (r01 + r10) / (4 * x), (r02 + r20) / (4 * x)
    elif biggest == r11:
        y = math.sqrt(max(1.0 - r00 + r11 - r22, 0.0)) / 2.0
        w, x, z = (r02 - r20) / (4 * y), (r01 + r10) / (4 * y), (r12 + r21) / (4 * y)
    else:
        z = math.sqrt(max(1.0 - r00 - r11 + r22, 0.0)) / 2.0
        w, x, y = (r10 - r01) / (4 * z), (r02 + r20) / (4 * z), (r12 + r21) / (4 * z)
    if w < 0.0:
        w, x, y, z = -w, -x, -y, -z
    sin_half = math.sqrt(x * x + y * y + z * z)
    scale = 2.0 * math.atan2(sin_half, w) / sin_half if sin_half > 1e-12 else 2.0
    return np.array([x * scale, y * scale, z * scale])


def exp_so3(rotvec) -> np.ndarray:
    """Rotation matrix of a rotation vector (Rodrigues), for one vector."""
    x, y, z = (float(v) for v in rotvec)
    angle = math.sqrt(x * x + y * y + z * z)
    if angle < 1e-9:
        return np.array([[1.0, -z, y], [z, 1.0, -x], [-y, x, 1.0]])
    kx, ky, kz = x / angle, y / angle, z / angle
    c, s = math.cos(angle), math.sin(angle)
    v = 1.0 - c
    return np.array([[c + kx * kx * v, kx * ky * v - kz * s, kx * kz * v + ky * s],
                     [ky * kx * v + kz * s, c + ky * ky * v, ky * kz * v - kx * s],
                     [kz * kx * v - ky * s, kz * ky * v + kx * s, c + kz * kz * v]])


def pose_to_frame(pose) -> tuple[np.ndarray, np.ndarray]:
    pose = np.asarray(pose, dtype=float)
    return exp_so3(pose[3:]), pose[:3].copy()


def frame_to_pose(rotation: np.ndarray, position: np.ndarray) -> np.ndarray:
    return np.concatenate([position, log_so3(rotation)])


_EYE6 = np.eye(6)

# A cycle's IK ends after a Newton step of at most this much per joint without evaluating the
# pose it reaches: what such a step leaves is second order in it, at most 1/2 (6 x 3e-6 rad)^2
# x 1.5 m (the reach of a UR10 with its tool, the longest lever a joint turns) = 2.4e-10 m, below
# the tracking tolerance of 1e-9 m. A motion's last cycle still solves to 1e-12 m.
TRACKING_FINAL_STEP_RAD = 3e-6


# the cyclic permutation taking z to each axis (x, y, z): a proper rotation, so a turn about
# the axis is this times a turn about z times its transpose
_Z_TO_AXIS = [np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),
              np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]),
              np.eye(3)]


def _rigid(elements, values) -> tuple[np.ndarray, np.ndarray]:
    """The rigid transform (rotation, translation in m) of chain elements no joint drives."""
    rotation, position = np.eye(3), np.zeros(3)
    for el, v in zip(elements, values):
        if el.is_rotation:
            j, k = (el.axis + 1) % 3, (el.axis + 2) % 3
            turn = np.eye(3)
            turn[j, j] = turn[k, k] = math.cos(v)
            turn[k, j], turn[j, k] = math.sin(v), -math.sin(v)
            rotation = rotation @ turn
        else:
            position = position + rotation[:, el.axis] * (v / 1000.0)
    return rotation, position


def joint_body_frames(model: KinematicModel, params) -> tuple[list[np.ndarray], np.ndarray]:
    """The arm of `params` as a physics engine's body tree wants it: for each joint, the 4x4 (m) of
    the body it turns in its parent body's frame at zero joint angle (the joint turns about that
    body's z through its origin), and the last body -> flange. For arms whose every joint is a turn
    about z driven by that joint alone (as the modified-DH files are); ValueError otherwise."""
    chain = model.chains["flange"]
    elements = chain.elements
    params = np.asarray(params, dtype=float)
    values = [float(params[el.param]) if el.param >= 0 else float(el.constant) for el in elements]
    driven = [i for i, el in enumerate(elements) if el.joints]
    if len(driven) != model.n_joints or any(
            not elements[i].is_rotation or elements[i].axis != 2 or elements[i].joints != ((j, 1.0),)
            for j, i in enumerate(driven)):
        raise ValueError(f"{model.name}: not a chain of joints turning about z, one each")
    frames = []
    for a, i in zip([0, *(d + 1 for d in driven)], driven):
        rotation, position = _rigid(elements[a:i], values[a:i])
        frame = np.eye(4)
        frame[:3, :3] = rotation @ _rigid(elements[i:i + 1], values[i:i + 1])[0]  # the joint's zero offset
        frame[:3, 3] = position
        frames.append(frame)
    rotation, position = _rigid(elements[driven[-1] + 1:], values[driven[-1] + 1:])
    rest = np.eye(4)
    rest[:3, :3], rest[:3, 3] = rotation, position
    end = np.array(chain.end, dtype=float)
    end[:3, 3] = end[:3, 3] / 1000.0
    return frames, rest @ end


class ArmKinematics:
    """Flange and TCP frames and the TCP Jacobian of a model's flange chain, in metres.

    ``solvers.geometry.chain.forward`` is vectorised over many poses and costs about a millisecond
    for one; the controller needs one pose several times per 2 ms cycle. So the same chain
    elements are evaluated here for a single pose, and checked against ``forward`` once at
    construction so both always describe the same arm.
    """

    def __init__(self, model: KinematicModel, params: np.ndarray | None = None):
        """The model's nominal geometry (what a controller computes with), or `params`
        (the arm as really built, for the simulated physics)."""
        self.model = model
        self.chain = model.chains["flange"]
        self.n_joints = model.n_joints
        elements = self.chain.elements
        params = np.asarray(model.nominal if params is None else params, dtype=float)
        base = [float(params[el.param]) if el.param >= 0 else float(el.constant) for el in elements]
        # The elements no joint drives are one rigid transform between two driven ones, and each
        # driven element acts on the z axis of a frame turned so (a cyclic permutation of the axes,
        # undone in the next rigid transform): the walk composes 6 rigid transforms and 6 turns
        # about z instead of the 24 elements, in a dozen plain floats.
        driven = [i for i, el in enumerate(elements) if el.joints]
        self._base = np.array([base[i] for i in driven])
        self._coupling = np.zeros((len(driven), self.n_joints))
        for row, i in enumerate(driven):
            for j, c in elements[i].joints:
                self._coupling[row, j] += c
        self._driven = [(elements[i].is_rotation, tuple(elements[i].joints)) for i in driven]
        self._fixed = []  # the rigid transform before each driven element: 9 rotation entries row by row, 3 of translation
        undo = np.eye(3)  # back from the previous driven element's turned frame
        for a, i in zip([0, *(d + 1 for d in driven)], driven):
            rotation, position = _rigid(elements[a:i], base[a:i])
            turn = _Z_TO_AXIS[elements[i].axis]
            self._fixed.append((*(undo @ rotation @ turn).ravel().tolist(), *(undo @ position).tolist()))
            undo = turn.T
        rotation, position = _rigid(elements[driven[-1] + 1:], base[driven[-1] + 1:])
        end = self.chain.end
        self._end = (*(undo @ rotation @ end[:3, :3]).ravel().tolist(),
                     *(undo @ (position + rotation @ end[:3, 3] / 1000.0)).tolist())
        self._tool_key, self._tool_frame = None, None
        self._check_against_chain(params)

    def _check_against_chain(self, params) -> None:
        q = np.random.default_rng(0).uniform(-np.pi, np.pi, (4, self.n_joints))
        rot, org = forward(self.chain, params, q)
        for i in range(len(q)):
            r, p, _ = self._walk(q[i], want_frames=False)
            if np.abs(r - rot[i]).max() > 1e-9 or np.abs(p * 1000.0 - org[i]).max() > 1e-7:
                raise AssertionError(f"{self.model.name}: single-pose kinematics disagree with the chain")

    def _walk(self, q, want_frames: bool):
        """End rotation, end position (m) and, if wanted, (axis, origin, couplings) of each
        joint-driven element. Plain floats: for one pose they beat numpy's call overhead."""
        values = (self._base + self._coupling @ np.asarray(q, dtype=float)).tolist()
        xx, xy, xz, yx, yy, yz, zx, zy, zz = 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0  # the rotation's columns
        px = py = pz = 0.0
        frames = []
        for (is_rotation, joints), v, fixed in zip(self._driven, values, self._fixed):
            m00, m01, m02, m10, m11, m12, m20, m21, m22, tx, ty, tz = fixed
            px, py, pz = (px + xx * tx + yx * ty + zx * tz, py + xy * tx + yy * ty + zy * tz,
                          pz + xz * tx + yz * ty + zz * tz)
            xx, xy, xz, yx, yy, yz, zx, zy, zz = (
                xx * m00 + yx * m10 + zx * m20, xy * m00 + yy * m10 + zy * m20, xz * m00 + yz * m10 + zz * m20,
                xx * m01 + yx * m11 + zx * m21, xy * m01 + yy * m11 + zy * m21, xz * m01 + yz * m11 + zz * m21,
                xx * m02 + yx * m12 + zx * m22, xy * m02 + yy * m12 + zy * m22, xz * m02 + yz * m12 + zz * m22)
            if want_frames:
                frames.append((is_rotation, (zx, zy, zz), (px, py, pz), joints))
            if is_rotation:  # about z
                c, s = math.cos(v), math.sin(v)
                xx, xy, xz, yx, yy, yz = (c * xx + s * yx, c * xy + s * yy, c * xz + s * yz,
                                          c * yx - s * xx, c * yy - s * xy, c * yz - s * xz)
            else:  # along z, in mm
                v = v / 1000.0
                px, py, pz = px + v * zx, py + v * zy, pz + v * zz
        m00, m01, m02, m10, m11, m12, m20, m21, m22, tx, ty, tz = self._end
        rot = np.array([[xx * m00 + yx * m10 + zx * m20, xx * m01 + yx * m11 + zx * m21, xx * m02 + yx * m12 + zx * m22],
                        [xy * m00 + yy * m10 + zy * m20, xy * m01 + yy * m11 + zy * m21, xy * m02 + yy * m12 + zy * m22],
                        [xz * m00 + yz * m10 + zz * m20, xz * m01 + yz * m11 + zz * m21, xz * m02 + yz * m12 + zz * m22]])
        pos = np.array([px + xx * tx + yx * ty + zx * tz, py + xy * tx + yy * ty + zy * tz,
                        pz + xz * tx + yz * ty + zz * tz])
        return rot, pos, frames

    def _tool(self, tcp_offset) -> tuple[np.ndarray, np.ndarray]:
        key = tuple(np.asarray(tcp_offset, dtype=float).tolist())
        if key != self._tool_key:
            self._tool_key, self._tool_frame = key, pose_to_frame(key)
        return self._tool_frame

    def flange(self, q) -> tuple[np.ndarray, np.ndarray]:
        rot, pos, _ = self._walk(q, want_frames=False)
        return rot, pos

    def tcp_frame(self, q, tcp_offset) -> tuple[np.ndarray, np.ndarray]:
        rf, pf = self.flange(q)
        rt, pt = self._tool(tcp_offset)
        return rf @ rt, pf + rf @ pt

    def tcp_pose(self, q, tcp_offset) -> np.ndarray:
        return frame_to_pose(*self.tcp_frame(q, tcp_offset))

    def jacobian(self, q, tcp_offset) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """TCP frame and its 6 x n geometric Jacobian (linear m/rad over angular rad/rad)."""
        rf, pf, frames = self._walk(q, want_frames=True)
        rt, pt = self._tool(tcp_offset)
        p = pf + rf @ pt
        x, y, z = p.tolist()
        jac = [[0.0] * self.n_joints for _ in range(6)]
        for is_rotation, (ax, ay, az), (ox, oy, oz), joints in frames:
            if is_rotation:
                dx, dy, dz = x - ox, y - oy, z - oz
                column = (ay * dz - az * dy, az * dx - ax * dz, ax * dy - ay * dx, ax, ay, az)
            else:  # the element's value is in mm, the TCP's position in m
                column = (ax / 1000.0, ay / 1000.0, az / 1000.0, 0.0, 0.0, 0.0)
            for j, c in joints:
                for row in range(6):
                    jac[row][j] += c * column[row]
        return rf @ rt, p, np.array(jac)

    def ik(self, rotation: np.ndarray, position: np.ndarray, q_seed, tcp_offset, *,
           tol: float = 1e-12, max_iter: int = 60, damping: float = 1e-4, final_step_rad: float = 0.0) -> np.ndarray:
        """Joints putting the TCP at (rotation, position), near q_seed (damped least squares).

        ``final_step_rad`` > 0: a Newton step no joint of which exceeds it ends the search
        without evaluating the pose it reaches (see :data:`TRACKING_FINAL_STEP_RAD`)."""
        q = np.array(q_seed, dtype=float)
        for _ in range(max_iter):
            r, p, jac = self.jacobian(q, tcp_offset)
            err = np.concatenate([position - p, log_so3(rotation @ r.T)])
            if np.abs(err).max() < tol:
                return q
            lam2 = damping**2 * min(1.0, float(err @ err) * 1e4)  # damping fades near the goal
            dq = jac.T @ np.linalg.solve(jac @ jac.T + lam2 * _EYE6, err)
            biggest = np.abs(dq).max()
            q += dq / max(1.0, biggest / 0.2)
            if biggest < final_step_rad:
                return q
        r, p = self.tcp_frame(q, tcp_offset)
        err = np.concatenate([position - p, log_so3(rotation @ r.T)])
        if np.abs(err).max() < max(tol, 1e-9) * 10:
            return q
        raise MotionFault(f"no inverse kinematics solution within {max_iter} iterations "
                          f"(residual {np.abs(err).max():.2e}) for pose at {np.round(position, 4).tolist()} m")


class Trapezoid:
    """Time-optimal rest-to-rest profile over a length with speed and acceleration limits."""

    def __init__(self, length: float, speed: float, accel: float):
        self.length = max(float(length), 0.0)
        speed = max(float(speed), 1e-9)
        accel = max(float(accel), 1e-9)
        if self.length * accel < speed**2:  # never reaches cruise speed: triangle
            speed = np.sqrt(self.length * accel)
        self.speed, self.accel = speed, accel
        self.t_ramp = speed / accel
        self.duration = 0.0 if self.length == 0 else self.length / speed + self.t_ramp

    def position(self, t: float) -> float:
        if t >= self.duration:
            return self.length
        if t < self.t_ramp:
            return 0.5 * self.accel * t * t
        if t > self.duration - self.t_ramp:
            rest = self.duration - t
            return self.length - 0.5 * self.accel * rest * rest
        return 0.5 * self.accel * self.t_ramp**2 + self.speed * (t - self.t_ramp)


class Motion:
    """A trajectory generator: ``step`` gives the joints one cycle later."""

    done = False

    def step(self, q: np.ndarray, dt: float) -> np.ndarray:
        raise NotImplementedError


class JointMove(Motion):
    def __init__(self, q_from, q_to, speed, accel):
        self.q_from = np.array(q_from, dtype=float)
        self.q_to = np.array(q_to, dtype=float)
        self.delta = self.q_to - self.q_from
        self.profile = Trapezoid(np.abs(self.delta).max(), speed, accel)
        self.t = 0.0

    def step(self, q, dt):
        self.t += dt
        if self.t >= self.profile.duration:
            self.done = True
            return self.q_to.copy()
        return self.q_from + self.delta * (self.profile.position(self.t) / self.profile.length)


class CartesianMotion(Motion):
    """A motion whose TCP follows a path in the base frame, one IK a cycle."""

    kin: ArmKinematics
    tcp: np.ndarray
    _q_last: np.ndarray | None = None

    def _joints_for(self, rotation, position, q) -> np.ndarray:
        """The joints of the next cycle: the IK seeded where the joints' last step leads (a smooth
        path's next joints differ from that by the joint acceleration times a cycle squared), so one
        Newton step usually lands within :data:`TRACKING_FINAL_STEP_RAD`."""
        last = self._q_last
        seed = q if last is None or last.shape != q.shape else 2.0 * q - last
        q_next = self.kin.ik(rotation, position, seed, self.tcp, tol=1e-9, max_iter=8,
                             final_step_rad=TRACKING_FINAL_STEP_RAD)
        self._q_last = np.array(q, dtype=float)
        return q_next


class LinearMove(CartesianMotion):
    def __init__(self, kin: ArmKinematics, q_from, tcp_offset, pose_to, speed, accel):
        self.kin, self.tcp = kin, np.array(tcp_offset, dtype=float)
        self.r0, self.p0 = kin.tcp_frame(q_from, self.tcp)
        self.r1, self.p1 = pose_to_frame(pose_to)
        self.turn = log_so3(self.r1 @ self.r0.T)
        length = max(np.linalg.norm(self.p1 - self.p0), np.linalg.norm(self.turn) * ROTATION_RADIUS_M)
        self.profile = Trapezoid(length, speed, accel)
        self.t = 0.0
        # solve the end first, so an unreachable target fails before the arm moves
        self.q_end = kin.ik(self.r1, self.p1, q_from, self.tcp)

    def step(self, q, dt):
        self.t += dt
        if self.t >= self.profile.duration:
            self.done = True
            return self.kin.ik(self.r1, self.p1, q, self.tcp)
        s = self.profile.position(self.t) / self.profile.length
        rotation = exp_so3(self.turn * s) @ self.r0
        return self._joints_for(rotation, self.p0 + s * (self.p1 - self.p0), q)


class SpeedLinear(CartesianMotion):
    """speedl: the TCP twist ramps to ``twist`` [vx, vy, vz, wx, wy, wz] (base frame) and holds."""

    def __init__(self, kin: ArmKinematics, q_from, tcp_offset, twist, accel):
        self.kin, self.tcp = kin, np.array(tcp_offset, dtype=float)
        self.rotation, self.position = kin.tcp_frame(q_from, self.tcp)
        self.twist = np.array(twist, dtype=float)
        speed = np.linalg.norm(self.twist[:3]) or np.linalg.norm(self.twist[3:]) * ROTATION_RADIUS_M
        self.t_ramp = speed / max(float(accel), 1e-9)
        self.t = 0.0

    def step(self, q, dt):
        self.t += dt
        scale = 1.0 if self.t >= self.t_ramp else self.t / self.t_ramp
        self.position = self.position + self.twist[:3] * scale * dt
        self.rotation = exp_so3(self.twist[3:] * scale * dt) @ self.rotation
        return self._joints_for(self.rotation, self.position, q)


class StopMotion(Motion):
    """Decelerate the joint velocity ``qd`` to rest over ``duration`` seconds."""

    def __init__(self, q_from, qd, duration):
        self.q_from, self.qd = np.array(q_from, dtype=float), np.array(qd, dtype=float)
        self.duration = float(duration)
        self.t = 0.0
        self.done = self.duration <= 0.0

    def step(self, q, dt):
        if self.duration <= 0.0:  # already at rest
            self.done = True
            return self.q_from.copy()
        self.t = min(self.t + dt, self.duration)
        self.done = self.t >= self.duration
        return self.q_from + self.qd * (self.t - self.t**2 / (2.0 * self.duration))


class MovingArm:
    """Joint state, tool frame, the active motion and the recent past (for tool_contact)."""

    HISTORY = 2500  # cycles kept for get_actual_joint_positions_history / tool_contact

    def __init__(self, kin: ArmKinematics, q0, dt: float = 0.002, contact=None):
        self.kin, self.dt = kin, dt
        self.q = np.array(q0, dtype=float)
        self.qd = np.zeros_like(self.q)
        self.tcp_offset = np.zeros(6)
        self.motion: Motion | None = None
        self.contact = contact or (lambda position: False)  # position (m) -> touching?
        self.q_history: deque = deque([self.q.copy()], maxlen=self.HISTORY)
        self.contact_history: deque = deque([False], maxlen=self.HISTORY)
        self._update_tcp()
        self._speed = np.zeros(6)
        self._moved: tuple | None = None  # the last cycle's TCP frames, before and after, until asked for the speed
        self.moving_s = 0.0  # how long the current motion has run

    @property
    def tcp_speed(self) -> np.ndarray:
        """The TCP's twist over the last cycle [vx, vy, vz, wx, wy, wz] (base frame), worked out
        when asked: the fake reports it every cycle, the in-process cell only when it stops."""
        if self._moved is not None:
            (r_old, p_old), (r_new, p_new) = self._moved
            self._speed = np.concatenate([(p_new - p_old) / self.dt, log_so3(r_new @ r_old.T) / self.dt])
            self._moved = None
        return self._speed

    @property
    def moving(self) -> bool:
        return self.motion is not None or bool(np.any(self.qd != 0.0))

    def step(self) -> None:
        """Advance one controller cycle; a MotionFault halts the arm and propagates."""
        q_old, (r_old, p_old) = self.q, self.tcp_frame
        if self.motion is not None:
            try:
                self.q = self.motion.step(self.q, self.dt)
            except MotionFault:
                self.halt()
                raise
            self.moving_s += self.dt
            if self.motion.done:
                self.motion = None
        at_rest = self.q is q_old
        self.qd = np.zeros_like(self.q) if at_rest else (self.q - q_old) / self.dt
        if self.motion is None and at_rest:
            self.moving_s = 0.0
        if not at_rest:  # the TCP only moves when the joints do
            self._update_tcp()
            self._moved = ((r_old, p_old), self.tcp_frame)
        else:
            self._speed, self._moved = np.zeros(6), None
        self.q_history.append(self.q.copy())
        self.contact_history.append(bool(self.contact(self.tcp_pose[:3])))

    def start(self, motion: Motion) -> Motion:
        self.motion = motion
        return motion

    def halt(self) -> None:
        """Stop dead (protective stop): no deceleration phase."""
        self.motion = None
        self.qd = np.zeros_like(self.q)

    def stop_joint(self, decel_rad_s2: float) -> StopMotion:
        peak = np.abs(self.qd).max()
        return self.start(StopMotion(self.q, self.qd, peak / max(decel_rad_s2, 1e-9)))

    def stop_linear(self, decel_m_s2: float) -> StopMotion:
        speed = np.linalg.norm(self.tcp_speed[:3])
        return self.start(StopMotion(self.q, self.qd, speed / max(decel_m_s2, 1e-9)))

    def set_tcp(self, tcp_offset) -> None:
        self.tcp_offset = np.array(tcp_offset, dtype=float)
        self._update_tcp()

    def _update_tcp(self) -> None:
        self.tcp_frame = self.kin.tcp_frame(self.q, self.tcp_offset)
        self.tcp_pose = frame_to_pose(*self.tcp_frame)

    def tool_contact(self) -> int:
        """URScript tool_contact: cycles back to just before the contact began, 0 if none."""
        steps = 0
        for touching in reversed(self.contact_history):
            if not touching:
                break
            steps += 1
        return steps

    def past_q(self, steps: int) -> np.ndarray:
        steps = int(np.clip(steps, 0, len(self.q_history) - 1))
        return self.q_history[-1 - steps].copy()
