"""How to touch a stylus so that the contacts determine the tool, and what they determine.

Pose design (:func:`design`): where on the tool and from which orientations the contacts
are made. Re-aiming (:func:`reaim`): moving a probe planned on the drawn tool so that it
lands as planned on the real one. Clearance (:func:`capsule_gap`): how far the tool's body
is from the stylus ball, to plan moves that cannot hit it.

Identifiability (:func:`determined`, :func:`null_directions`): the rank of the contact
model's Jacobian, read off its singular values; a direction the contacts do not see is
named and no value along it is reported. :func:`contact_jacobian` extends the model with
the arm's kinematic parameters (analytic, through :func:`cellcal.solvers.geometry.chain.point_jacobians`) to check
the claim of Chang et al. ("A Stylus-Based Calibration Method for Robotic Belt Grinding
Tools", Appl. Sci. 2025) that contacts on one stylus identify 20 DH errors, 6 tool and 3
stylus parameters: a small change of the parameters moves the flange, and the distance from the
stylus to the axis changes by minus the unit normal (axis toward stylus) dotted with how
far the axis point nearest the stylus moved.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import qr

from cellcal.solvers.geometry import se3
from cellcal.solvers.tool_frames import stylus as fitting
from cellcal.solvers.geometry.chain import forward, point_jacobians
from cellcal.solvers.geometry.inverse import inverse, tcp_frames, tcp_poses
from cellcal.solvers.geometry.robot_model import KinematicModel
from cellcal.solvers.tool_frames.stylus import Estimate, StylusFit, scales

STRUCTURAL_RTOL = 1e-9  # singular values below this times the largest: a direction the data do not see
HEIGHT_BAND = 0.15  # side contacts lie in the lowest and the highest 15 % of the heights
TOOL_NAMES = ("tool.x", "tool.y", "tool.z", "tool.rx", "tool.ry", "tool.rz")
STYLUS_NAMES = ("stylus.x", "stylus.y", "stylus.z")


# -- pose design ----------------------------------------------------------------------------------

def design(side_contacts: int, stations: int, tilt_deg: float, sides_deg: float,
           heights_mm: tuple[float, float], sweep_deg: float | None = None, seed: int = 0) -> list[tuple]:
    """Side contacts as (station, tilt_deg, tilt_azimuth_deg, side_deg, height_mm, angle_deg).

    The tool is held at `stations` orientations: tilted by `tilt_deg` across the side it is
    touched from (azimuth -90 or +90) or over the stylus (0), for sides swept from -sides_deg
    to +sides_deg, in a serpentine so that neighbours are close; the last station holds it
    straight. `angle_deg` is where on the circumference (tool frame) the contact is meant to
    be: station s covers the s-th sector of the circle, so together they go all round. Half
    the contacts of a station are in the lowest band of `heights_mm`, half in the highest
    (the axis direction is seen through the lever between them), stratified within each and
    visited in order, so that the tool moves little from one contact to the next.
    """
    tilted = stations - 1
    azimuths = (-90.0, 0.0, 90.0)
    plan = [(tilt_deg, azimuths[k % 3] if (k // 3) % 2 == 0 else azimuths[2 - k % 3],
             -sides_deg + 2 * sides_deg * k / max(tilted - 1, 1)) for k in range(tilted)] + [(0.0, 0.0, 0.0)]
    counts = np.diff(np.linspace(0, side_contacts, stations + 1).round().astype(int))
    rng = np.random.default_rng(seed)
    lo, hi = heights_mm
    band = HEIGHT_BAND * (hi - lo)
    out = []
    for s, ((tilt, azimuth, side), n) in enumerate(zip(plan, counts)):
        low, high = (n + 1) // 2, n // 2
        sweep = 360.0 / stations if sweep_deg is None else sweep_deg
        angles = s * 360.0 / stations + (np.arange(n) + 0.5) / n * sweep
        heights = np.r_[lo + (np.arange(low) + rng.random(low)) / low * band,  # stratified, in order
                        hi - (np.arange(high) + rng.random(high)) / max(high, 1) * band]
        angles = np.r_[angles[0::2], angles[1::2][::-1]]  # up the circle low, back down it high
        out += [(s, tilt, azimuth, side, float(h), float(a)) for h, a in zip(heights, angles)]
    return out


def reaim(estimate: Estimate, flange_rotation: np.ndarray, drawn_point_mm: np.ndarray, drawn_tip_mm,
          stylus_file_mm: np.ndarray, at_tip: bool) -> np.ndarray:
    """The base-frame translation (mm) that puts the real tool where a probe planned on the
    drawn tool and the file's stylus meant it to be, relative to the real stylus.

    A side probe aims the drawn axis point `drawn_point_mm` (flange) at the stylus: its real
    counterpart is the estimated axis point nearest it. An end-face probe (`at_tip`) aims the
    drawn tip: its counterpart is the estimated tip (or, before it is known, the drawn tip's
    foot on the estimated axis).
    """
    if at_tip and estimate.tip_mm is not None:
        real = estimate.tip_mm
    else:
        real = estimate.line.foot(np.asarray(drawn_tip_mm if at_tip else drawn_point_mm, float))
    return (estimate.stylus_mm - stylus_file_mm) + flange_rotation @ (np.asarray(drawn_point_mm, float) - real)


def capsule_gap(rotation: np.ndarray, position: np.ndarray, tip: np.ndarray, axis: np.ndarray, radius: float,
                length: float, centre: np.ndarray, ball_radius: float) -> np.ndarray:
    """Gap between a capsule tool (tip, axis from flange toward the tip, both in the flange
    frame; its rounding's centre `radius` behind the tip, reaching `length` back) and a ball,
    for flange poses (N, 3, 3), (N, 3). Negative: they overlap. Any consistent length unit."""
    front = position + rotation @ (tip - axis * radius)
    back = position + rotation @ (tip - axis * length)
    ab = back - front
    t = np.clip(np.einsum("ni,ni->n", centre - front, ab) / np.einsum("ni,ni->n", ab, ab), 0.0, 1.0)
    return np.linalg.norm(front + t[:, None] * ab - centre, axis=1) - radius - ball_radius


def linear_path(pose_from, pose_to, tool_pose, samples: int) -> tuple[np.ndarray, np.ndarray]:
    """Flange frames (S, 3, 3), (S, 3) along a TCP moved on a straight line from `pose_from`
    to `pose_to` ([x, y, z, rotation vector]), turning about one constant axis, as a linear
    move does; `tool_pose` is the TCP in the flange frame."""
    s = np.linspace(0.0, 1.0, samples)[:, None]
    r0 = se3.rotvec_to_matrix(np.asarray(pose_from[3:], float))
    turn = se3.matrix_to_rotvec(se3.rotvec_to_matrix(np.asarray(pose_to[3:], float)) @ r0.T)
    rot = se3.rotvec_to_matrix(s * turn) @ r0 @ se3.rotvec_to_matrix(np.asarray(tool_pose[3:], float)).T
    pos = pose_from[:3] + s * (np.asarray(pose_to[:3]) - pose_from[:3]) - rot @ np.asarray(tool_pose[:3], float)
    return rot, pos


def nearest_turn(q, near, limits) -> np.ndarray:
    """Joints `q` with each turned by whole turns to be nearest `near`, within `limits`."""
    out = np.array(q, float)
    for i, (v, ref) in enumerate(zip(out, near)):
        options = v + 2 * np.pi * np.arange(-2, 3)
        if limits is not None:
            options = options[(options >= limits[i][0]) & (options <= limits[i][1])]
        out[i] = options[np.argmin(np.abs(options - ref))] if len(options) else v
    return out


def path_gaps(model: KinematicModel, moves, q_start, tool_pose, tool_tip, tool_axis, tool_radius, tool_length,
              centre, ball_radius, samples: int = 24) -> np.ndarray:
    """The least gap (m) between a capsule tool and a ball along each of a sequence of moves
    from joints `q_start`: ("joint", q), ("linear", TCP pose) or ("contact", None) (where a
    contact search stops is not known in advance: the state stays, and its gap is NaN). A
    joint move is sampled in joint space, a linear one on its straight line; metres."""
    q = q_last = np.asarray(q_start, float)
    pose = tcp_poses(model, q, tool_pose)[0]
    out = np.full(len(moves), np.nan)
    for i, (kind, target) in enumerate(moves):
        if kind == "joint":
            if not np.allclose(tcp_poses(model, q, tool_pose)[0][:3], pose[:3]):
                q = inverse(model, pose, q_last, tool_pose)
            rot, pos = tcp_frames(model, q + np.linspace(0, 1, samples)[:, None] * (np.asarray(target) - q))
            q = q_last = np.asarray(target, float)
            pose = tcp_poses(model, q, tool_pose)[0]
        elif kind == "linear":
            rot, pos = linear_path(pose, target, tool_pose, samples)
            pose = np.asarray(target, float)
        else:
            continue
        out[i] = capsule_gap(rot, pos, tool_tip, tool_axis, tool_radius, tool_length, centre, ball_radius).min()
    return out


# -- recorded contacts and where their fit starts ---------------------------------------------------

@dataclass(frozen=True)
class Recorded:
    """Recorded contacts as the fit wants them. `kind` per row: coarse-face, axial, side, face."""

    kind: np.ndarray
    group: np.ndarray  # axial moves of one group share an orientation
    q: np.ndarray  # (N, n_joints) rad
    rotation: np.ndarray  # (N, 3, 3) flange, the controller's kinematics at q
    position_mm: np.ndarray  # (N, 3) flange origin, less the contact's mean overshoot
    approach: np.ndarray  # (N, 3) unit, base: the way the tool moved to touch

    @classmethod
    def of(cls, model: KinematicModel, q, kind, group, approach, speed_m_s, cycle_s: float) -> "Recorded":
        """The controller notices a contact at its next cycle: the recorded pose lies on average
        half a cycle's travel beyond the contact, which is taken off here."""
        rotation, position = tcp_frames(model, q)
        approach = np.asarray(approach, float)
        position = position - approach * (np.asarray(speed_m_s, float) * cycle_s / 2)[:, None]
        return cls(np.asarray(kind), np.asarray(group, int), np.asarray(q, float), rotation, position * 1e3, approach)

    def contacts(self, rows) -> fitting.Contacts:
        kind = np.where(self.kind[rows] == "face", fitting.FACE, fitting.SIDE)
        return fitting.Contacts(self.rotation[rows], self.position_mm[rows], kind)


def start_and_fit(data: Recorded, drawn: Estimate, stylus_radius_mm: float, tool_radius_mm: float, *,
                  fit_radius: bool = True, end_shape: str = "round", loss: str = "soft_l1", noise_mm: float = 0.02,
                  plausible_mm: float = 10.0, plausible_deg: float = 5.0, coarse_only: bool = False):
    """(coarse estimate or None, fine fit or None) of recorded contacts.

    The coarse estimate is dropped when it is implausibly far from the drawing (a coarse touch
    went wrong); the fine fit of every contact but the coarse end-face touches starts from it
    and from the drawing, and keeps the better (:func:`.stylus.best_fit`)."""
    radius = tool_radius_mm + stylus_radius_mm
    try:
        first = fitting.coarse(data.rotation, data.position_mm, data.kind, data.group, data.approach,
                               stylus_radius_mm, radius, drawn.line.direction)
    except (ValueError, np.linalg.LinAlgError):
        first = None
    if first is not None and (np.linalg.norm(first.tip_mm - drawn.tip_mm) > plausible_mm or
                              first.line.direction @ drawn.line.direction < np.cos(np.deg2rad(plausible_deg))):
        first = None
    if coarse_only:
        return first, None
    found = fitting.best_fit(data.contacts(data.kind != "coarse-face"), [e for e in (first, drawn) if e],
                             stylus_radius_mm, radius, fit_radius, end_shape, loss=loss, noise_mm=noise_mm)
    return first, found


# -- what the data determine ----------------------------------------------------------------------

@dataclass(frozen=True)
class Determined:
    rank: int
    n_params: int
    singular_values: np.ndarray  # of the column-scaled Jacobian
    condition: float  # of the scaled normal equations (singular value ratio squared)
    undetermined: list[str]  # combinations of parameters the data do not see, in words
    null_space: np.ndarray  # (n_params, k): those directions, in the fit's own units


def null_directions(jac_scaled: np.ndarray, names, rtol: float = STRUCTURAL_RTOL) -> tuple[int, list[str]]:
    """Rank of a column-scaled Jacobian and its null directions in words ("d2 - d3").

    The dependent columns are those a pivoted QR puts last; each null direction is one of
    them moved together with the independent columns that compensate it exactly.
    """
    s = np.linalg.svd(jac_scaled, compute_uv=False)
    rank = int(np.sum(s > rtol * s[0])) if len(s) and s[0] > 0 else 0
    _, _, piv = qr(jac_scaled, pivoting=True, mode="economic")
    independent, dependent = piv[:rank], piv[rank:]
    words = []
    for col in dependent:
        coef, *_ = np.linalg.lstsq(jac_scaled[:, independent], jac_scaled[:, col], rcond=None)
        v = np.zeros(jac_scaled.shape[1])
        v[col] = 1.0
        v[independent] = -coef
        v /= np.abs(v).max()
        terms = [(v[i], names[i]) for i in np.argsort(-np.abs(v)) if abs(v[i]) > 0.01]
        text = " ".join(f"{'-' if a < 0 else '+'} {'' if abs(abs(a) - 1) < 0.005 else f'{abs(a):.2g}*'}{n}"
                        for a, n in terms)
        words.append(text[2:] if text.startswith("+ ") else text)
    return rank, words


def determined(fit_result: StylusFit, max_std_mm: float = 1.0) -> Determined:
    """Rank and conditioning of a stylus fit's own Jacobian; a parameter whose standard
    deviation exceeds `max_std_mm` (angles times ANGLE_LENGTH_MM) counts as undetermined too."""
    scale = scales(fit_result.names)  # mm at the contacts per unit of each parameter
    j = fit_result.jacobian / scale
    rank, words = null_directions(j, fit_result.names)
    _, s, vt = np.linalg.svd(j, full_matrices=True)
    s = np.r_[s, np.zeros(len(scale) - len(s))]
    condition = float((s[0] / s[-1]) ** 2) if s[-1] > 0 else float("inf")
    null = (vt[rank:] / scale).T
    std = np.sqrt(np.abs(np.diag(fit_result.covariance))) * scale
    loose = [i for i, sd in enumerate(std) if sd > max_std_mm]
    if rank == len(scale):
        words += [f"{fit_result.names[i]} (+-{std[i]:.3g} mm at the contacts)" for i in loose]
        null = np.concatenate([null, np.eye(len(scale))[:, loose]], axis=1)
    return Determined(rank, len(scale), s, condition, words, null)


def contact_jacobian(model: KinematicModel, params: np.ndarray, q: np.ndarray, tool_pose_mm: np.ndarray,
                     axis_point_mm: np.ndarray, axis_direction: np.ndarray, stylus_mm: np.ndarray):
    """Distances from the stylus to the tool axis (N,), and their Jacobian (N, n_params + 9)
    over [kinematic parameters, tool twist (mm, rad; T' = T Exp(d), translation then rotation,
    in T), stylus (mm)].

    tool_pose_mm: flange -> T [x, y, z (mm), rotation vector]; the axis is the line through
    `axis_point_mm` along `axis_direction`, both in T.
    """
    q = np.atleast_2d(q)
    chain = model.chains[model.default_chain]
    rot_t = se3.rotvec_to_matrix(tool_pose_mm[3:])
    a_f = tool_pose_mm[:3] + rot_t @ axis_point_mm  # the axis in the flange frame
    d_f = rot_t @ axis_direction
    rot, org = forward(chain, params, q)
    s = np.einsum("nji,nj->ni", rot, stylus_mm - org)  # the stylus in the flange frame
    foot = a_f + ((s - a_f) @ d_f)[:, None] * d_f
    normal_f = s - foot
    dist = np.linalg.norm(normal_f, axis=1)
    normal_f /= dist[:, None]
    _, jp, _, _ = point_jacobians(chain, params, q, foot, model.n_params, model.n_joints)
    normal_b = np.einsum("nij,nj->ni", rot, normal_f)
    j_kin = -np.einsum("ni,nik->nk", normal_b, jp)
    x_t = (foot - tool_pose_mm[:3]) @ rot_t  # the foot in T
    n_t = normal_f @ rot_t  # the normal in T
    j_tool = np.concatenate([-n_t, -np.cross(x_t, n_t)], axis=1)
    return dist, np.concatenate([j_kin, j_tool, normal_b], axis=1)


def rank_report(model: KinematicModel, q: np.ndarray, tool_pose_mm, axis_point_mm, axis_direction, stylus_mm,
                kinematic: tuple[str, ...], reach_mm: float = 500.0) -> dict:
    """Rank of [the named kinematic parameters, tool 6, stylus 3] for contacts at joints `q`
    (nominal geometry), and the directions the contacts cannot see, named. Angles are scaled
    by `reach_mm` so that every column moves a contact by about a millimetre."""
    _, j = contact_jacobian(model, model.nominal, q, np.asarray(tool_pose_mm, float),
                            np.asarray(axis_point_mm, float), np.asarray(axis_direction, float),
                            np.asarray(stylus_mm, float))
    cols = [model.index(n) for n in kinematic] + list(range(model.n_params, model.n_params + 9))
    names = tuple(kinematic) + TOOL_NAMES + STYLUS_NAMES
    scale = np.array([reach_mm if n.startswith(("theta", "alpha", "tool.r")) else 1.0 for n in names])  # mm per unit
    rank, words = null_directions(j[:, cols] / scale, names)
    return {"parameters": len(names), "rank": rank, "not_identifiable": words, "names": names}
