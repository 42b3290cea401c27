"""ISO 9283 pose and distance characteristics on constructed data with known answers; the command."""
import json

import numpy as np
import pytest

from cellcal.solvers.identification.iso9283 import characteristics, cube_points, distance_characteristics, pose_characteristics


def test_cube_points_sit_on_the_diagonal_plane_at_10_percent_of_the_diagonal():
    p = cube_points([100.0, 0.0, 500.0], 400.0)
    assert p[0] == pytest.approx([100.0, 0.0, 500.0])
    diagonal = 400.0 * np.sqrt(3.0)  # the rectangle's diagonal is the cube's space diagonal
    corner = np.array([100.0, 0.0, 500.0]) + np.array([-200.0, -200.0, -200.0])
    assert np.linalg.norm(p[1] - corner) == pytest.approx(0.1 * diagonal)
    assert np.linalg.norm(p[1] - p[3]) == pytest.approx(0.8 * diagonal)  # P2 and P4: ends of one diagonal
    assert np.linalg.norm(p[2] - p[4]) == pytest.approx(0.8 * diagonal)
    d = p[1:] - p[0]
    assert np.allclose(d[:, 0], d[:, 2])  # all in the plane x = z through the centre


def test_pose_accuracy_and_repeatability_match_hand_computed_values():
    commanded = np.array([10.0, 20.0, 30.0])
    offset = np.array([0.3, -0.4, 0.0])  # barycentre off by 0.5 mm
    # six attained positions at 0.1 mm from the barycentre (+-x, +-y, +-z): l_j all 0.1, S_l 0
    spread = 0.1 * np.vstack([np.eye(3), -np.eye(3)])
    pc = pose_characteristics("P1", commanded, commanded + offset + spread)
    assert pc.ap_mm == pytest.approx(0.5, abs=1e-12)
    assert pc.ap_xyz_mm == pytest.approx((0.3, -0.4, 0.0), abs=1e-12)
    assert pc.rp_mm == pytest.approx(0.1, abs=1e-12) and pc.s_l_mm == pytest.approx(0.0, abs=1e-12)
    # two at 0.1 and two at 0.3 along x, symmetric: l = (0.1, 0.1, 0.3, 0.3), l_bar 0.2,
    # S_l = sqrt(4 * 0.01 / 3), RP = 0.2 + 3 * 0.11547 = 0.54641
    x = commanded + np.array([[0.1, 0, 0], [-0.1, 0, 0], [0.3, 0, 0], [-0.3, 0, 0]])
    pc = pose_characteristics("P2", commanded, x)
    assert pc.ap_mm == pytest.approx(0.0, abs=1e-12)
    assert pc.rp_mm == pytest.approx(0.2 + 3 * np.sqrt(0.04 / 3), abs=1e-12)


def test_distance_accuracy_and_repeatability_match_hand_computed_values():
    a_c, b_c = np.zeros(3), np.array([300.0, 400.0, 0.0])  # D_c = 500
    a = np.zeros((3, 3))
    b = np.array([500.4, 500.0, 500.8])[:, None] * np.array([0.6, 0.8, 0.0])  # D_j = 500.4, 500.0, 500.8
    dc = distance_characteristics(("P2", "P4"), (a_c, b_c), a, b)
    assert dc.commanded_mm == pytest.approx(500.0)
    assert dc.mean_mm == pytest.approx(500.4, abs=1e-9) and dc.ad_mm == pytest.approx(0.4, abs=1e-9)
    # S_D = sqrt((0 + 0.16 + 0.16) / 2) = 0.4, RD = 3 S_D
    assert dc.rd_mm == pytest.approx(1.2, abs=1e-9)


def test_characteristics_groups_rows_by_pose_and_pairs_distances_by_cycle():
    rng = np.random.default_rng(0)
    points = cube_points([0.0, 0.0, 0.0], 200.0)
    pose = np.tile(["P1", "P2", "P3", "P4", "P5"], 30)
    cycle = np.repeat(np.arange(30), 5)
    commanded = points[np.tile(np.arange(5), 30)]
    bias = np.array([[0.2, 0, 0], [0, 0.3, 0], [0, 0, 0.4], [0.1, 0.1, 0], [0, 0, 0]])
    attained = commanded + bias[np.tile(np.arange(5), 30)] + rng.normal(scale=0.01, size=(150, 3))
    poses, distance = characteristics(pose, cycle, commanded, attained)
    assert [p.pose for p in poses] == ["P1", "P2", "P3", "P4", "P5"] and all(p.n == 30 for p in poses)
    assert [p.ap_mm for p in poses] == pytest.approx([0.2, 0.3, 0.4, np.sqrt(0.02), 0.0], abs=0.01)
    assert all(0.01 < p.rp_mm < 0.06 for p in poses)  # 3-D noise of 0.01 per axis: l_bar ~0.016, + 3 S_l
    assert distance is not None and distance.n == 30
    # P2 and P4 biases differ by (0.1, -0.2, 0): the distance changes by its component along P4 - P2
    direction = (points[3] - points[1]) / np.linalg.norm(points[3] - points[1])
    assert distance.ad_mm == pytest.approx(np.dot([0.1, -0.2, 0.0], direction), abs=0.01)


def _iso_file(path, bias_mm, cycles=4):
    """ur5e driven to the cube points' joints; measured = the model's position + a bias per pose +
    +-0.1 mm along x alternating by cycle (so RP = 0.1 exactly, with 4 cycles)."""
    from cellcal.config.robot_files import load_robot
    from cellcal.measurements.writer import write_measurements
    from cellcal.solvers.geometry.chain import forward

    model = load_robot("ur5e")
    q5 = np.deg2rad([[0, -90, 90, -90, -90, 0], [10, -80, 80, -90, -90, 0], [20, -100, 95, -85, -90, 0],
                     [-10, -95, 100, -95, -90, 0], [-20, -85, 85, -90, -90, 10]])
    order = np.tile(np.arange(5), cycles)
    q = q5[order]
    _, p = forward(model.chains["flange"], model.nominal, q)
    sign = np.where(np.repeat(np.arange(cycles), 5) % 2 == 0, 1.0, -1.0)
    measured = p + np.asarray(bias_mm)[order] + 0.1 * sign[:, None] * np.array([1.0, 0, 0])
    write_measurements(path, q_rad=q, xyz_mm=measured,
                       extra={"pose": [f"P{i + 1}" for i in order], "cycle": list(np.repeat(np.arange(cycles), 5))})
    return np.linalg.norm(p[1] - p[3])


def test_iso9283_command_reports_known_accuracy_and_repeatability(tmp_path, capsys):
    from cellcal.cli.main import main

    bias = np.array([[0.5, 0, 0], [0, 0.2, 0], [0, 0, 0], [0, 0, -0.3], [0.3, 0.4, 0]])
    _iso_file(tmp_path / "iso.csv", bias)
    assert main(["iso9283", "--robot", "ur5e", "--data", str(tmp_path / "iso.csv"), "--json",
                 "--report", str(tmp_path / "rep")]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [p["pose"] for p in doc["poses"]] == ["P1", "P2", "P3", "P4", "P5"]
    assert [p["AP_mm"] for p in doc["poses"]] == pytest.approx([0.5, 0.2, 0.0, 0.3, 0.5], abs=1e-9)
    assert [p["RP_mm"] for p in doc["poses"]] == pytest.approx([0.1] * 5, abs=1e-9)
    assert doc["distance"]["n"] == 4
    assert (tmp_path / "rep" / "iso9283_ap_rp.png").stat().st_size > 1000


def test_iso9283_command_refuses_data_without_poses(tmp_path, capsys):
    from cellcal.cli.main import main
    from cellcal.measurements.writer import write_measurements

    write_measurements(tmp_path / "plain.csv", q_rad=np.zeros((3, 6)), xyz_mm=np.ones((3, 3)))
    assert main(["iso9283", "--robot", "ur5e", "--data", str(tmp_path / "plain.csv")]) == 2
    assert "missing column 'pose'" in capsys.readouterr().err


@pytest.mark.slow
def test_simulated_iso9283_campaign_before_after_compensation(tmp_path, capsys):
    from cellcal.cli.main import main

    assert main(["sim-campaign", "--iso9283", "--robot", "ur10e", "--poses", "150", "--cycles", "10",
                 "--seed", "2", "--out", str(tmp_path), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    before, after, compensated = (doc["cases"][k] for k in ("before calibration", "after calibration",
                                                               "after compensation"))
    assert compensated["AP_max_mm"] < 0.3 * before["AP_max_mm"]
    assert after["AP_max_mm"] < 0.3 * before["AP_max_mm"]
    # the same arm and cycles: repeatability does not depend on the model used to command it
    assert 0.5 < compensated["RP_max_mm"] / before["RP_max_mm"] < 2.0
    for name in ("iso9283.html", "iso9283_scatter.png", "iso9283_ap_rp.png"):
        assert (tmp_path / "report" / name).stat().st_size > 1000
    assert (tmp_path / "calibrated.yaml").exists() and (tmp_path / "iso_compensated.csv").exists()
