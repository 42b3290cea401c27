"""The handshake's result: robot b's base and both needle tips with their standard
deviations, the gates every result passes (residual, conditioning, identifiability,
plausibility of the base against where it was installed and of each tip against its
drawing), and the frame in the units people read and as lines for the cell file."""
from __future__ import annotations

import numpy as np

from cellcal.config.cells import Cell
from cellcal.solvers.tool_frames import handshake as hs
from cellcal.solvers.geometry import se3
from cellcal.routines.framework import gates
from cellcal.routines.framework.base import Gate, Parameter, Result, frame_text
from cellcal.routines.framework.drawing import meeting_points
from cellcal.routines.framework.tool_frame import TIP_ONLY

PLAUSIBLE_BASE_MM = 30.0  # a base found this far from where it was installed is doubted ...
PLAUSIBLE_BASE_DEG = 2.0  # ... or turned this far
MAX_STD_FACTOR = 1.0  # a frame coordinate whose std is above its target is not determined


def handshake_result(name, dataset, cell: Cell, options, fit: hs.HandshakeFit, design: hs.PlanQuality,
                     points_mm) -> Result:
    """`points_mm` (N, 3): where robot a's fitted tip was at each meeting, in a's base frame."""
    n = len(fit.residuals_mm)
    expected = float(np.sqrt(2.0) * options.repeatability_mm * np.sqrt(max(3 * n - hs.N_UNKNOWNS, 1) / (3 * n)))
    rms = float(np.sqrt(np.mean(np.sum(fit.residuals_mm**2, axis=1))))
    pose = fit.pose
    installed = cell.robots["b"].base_pose
    turn = se3.rotvec_to_matrix(pose[3:]) @ se3.rotvec_to_matrix(installed[3:]).T
    moved_mm = float(np.linalg.norm(pose[:3] - installed[:3]) * 1e3)
    moved_deg = float(np.rad2deg(np.linalg.norm(se3.matrix_to_rotvec(turn))))
    std_mm = float(np.linalg.norm(fit.std[3:6]))
    std_deg = float(np.rad2deg(np.linalg.norm(fit.std[:3])))
    undetermined = [f"base position (std {std_mm:.4f} mm)"] if std_mm > MAX_STD_FACTOR * options.target_mm else []
    if std_deg > MAX_STD_FACTOR * options.target_deg:
        undetermined.append(f"base rotation (std {std_deg:.5f} deg)")
    plausible = moved_mm <= PLAUSIBLE_BASE_MM and moved_deg <= PLAUSIBLE_BASE_DEG
    gate_list = [gates.residual(rms, expected), gates.conditioning(fit.condition), gates.identifiability(undetermined),
                 Gate("plausibility", plausible, moved_mm, PLAUSIBLE_BASE_MM,
                      f"robot b's base {moved_mm:.3f} mm and {moved_deg:.4f} deg from where [robots.b] installed it "
                      f"(limits {PLAUSIBLE_BASE_MM:g} mm, {PLAUSIBLE_BASE_DEG:g} deg)"
                      + ("" if plausible else ": has robot b been moved, or is [robots.b] base_m wrong?"))]
    for letter, tip in (("a", fit.tip_a_mm), ("b", fit.tip_b_mm)):
        drawn = cell.robots[letter].tool
        gate = gates.plausible_tool(np.concatenate([tip / 1e3, drawn.tcp_pose[3:]]), drawn, determines=TIP_ONLY)
        gate_list.append(Gate(f"plausibility tip {letter}", gate.passed, gate.value, gate.limit, gate.why))
    params = [Parameter(f"base_b_{c}_mm", float(fit.translation_mm[j]), float(fit.std[3 + j]), "mm")
              for j, c in enumerate("xyz")]
    rotvec = pose[3:]
    params += [Parameter(f"base_b_r{c}_deg", float(np.rad2deg(rotvec[j])), float(np.rad2deg(fit.std[j])), "deg")
               for j, c in enumerate("xyz")]
    for letter, tip, off in (("a", fit.tip_a_mm, 6), ("b", fit.tip_b_mm, 9)):
        params += [Parameter(f"tip_{letter}_{c}_mm", float(tip[j]), float(fit.std[off + j]), "mm")
                   for j, c in enumerate("xyz")]
    frame = {"from": "robot a base", "to": "robot b base",
             "x_mm": float(fit.translation_mm[0]), "y_mm": float(fit.translation_mm[1]),
             "z_mm": float(fit.translation_mm[2]), "rx_deg": float(np.rad2deg(rotvec[0])),
             "ry_deg": float(np.rad2deg(rotvec[1])), "rz_deg": float(np.rad2deg(rotvec[2])),
             "std_mm": fit.std[3:6].tolist(), "std_deg": np.rad2deg(fit.std[:3]).tolist(), "pose_m_rad": pose.tolist(),
             "change_from_cell_file_mm": moved_mm, "change_from_cell_file_deg": moved_deg,
             "cell_file": "robots:\n  b:\n    base_m: [" + ", ".join(f"{v:.7f}" for v in pose[:3])
                          + "]\n    base_rotvec_deg: [" + ", ".join(f"{np.rad2deg(v):.6f}" for v in rotvec) + "]"}
    start_turn = se3.matrix_to_rotvec(fit.start_rotation.T @ fit.rotation)
    notes = [f"robot b's base in robot a's frame: {frame_text(frame, angle_digits=5, lean=False)} (+- {std_mm:.4f} mm, "
             f"{std_deg:.5f} deg); for the cell file: " + " ".join(frame["cell_file"].split()),
             f"{n} meeting points, conditioning {fit.points.condition:.3g} (spread "
             f"{np.round(fit.points.spread_mm, 1).tolist()} mm RMS along their principal axes); the fit's condition "
             f"{fit.condition:.3g}",
             (f"standard deviations from the residual's own noise, {fit.sigma0_mm:.4f} mm per axis" if
              fit.sigma_used_mm == fit.sigma0_mm else f"only {3 * n - hs.N_UNKNOWNS} spare equations: standard "
              f"deviations from the stated repeatability ({fit.sigma_used_mm:.4f} mm per axis for both arms), not "
              "from the residual"),
             f"one fit of the frame and both needle tips; the closed-form start with the drawn tips was "
             f"{np.linalg.norm(fit.start_translation_mm - fit.translation_mm):.3f} mm and "
             f"{np.rad2deg(np.linalg.norm(start_turn)):.4f} deg from it"]
    extra = {"points_condition": fit.points.condition, "points_spread_mm": fit.points.spread_mm.tolist(),
             "points_out_of_plane_mm": fit.points.out_of_plane_mm, "fit_condition": fit.condition,
             "expected_base_error_mm": design.position_mm, "expected_base_error_deg": design.rotation_deg,
             "base_std_mm": std_mm, "base_std_deg": std_deg, "sigma0_mm": fit.sigma0_mm,
             "tip_a_mm": fit.tip_a_mm.tolist(), "tip_b_mm": fit.tip_b_mm.tolist(),
             "meeting_residuals_mm": np.linalg.norm(fit.residuals_mm, axis=1).tolist()}
    return Result(name, params, fit.residuals_mm, expected, fit.condition, gate_list, frame=frame, notes=notes,
                  extra=extra, drawing=meeting_points(points_mm, fit.residuals_mm, expected / np.sqrt(3.0)))
