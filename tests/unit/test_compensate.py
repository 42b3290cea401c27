"""Target compensation: scored against the simulation's hidden truth, rows that fail reported, the CLI contract."""
import csv
import json
from dataclasses import replace

import numpy as np
import pytest

from cellcal.config.model_files import write_calibrated
from cellcal.config.robot_files import load_robot
from cellcal.cli.main import main
from cellcal.sims.physics.physical_arm import HiddenEffect, PhysicalArm
from cellcal.sims.physics.workspace import full_workspace
from cellcal.solvers.geometry import se3
from cellcal.solvers.analysis.analyze import AnalyzeOptions, analyze
from cellcal.solvers.compensation.calibrated_model import CalibratedModel, from_fit
from cellcal.solvers.compensation.compensate import JOINT_LIMITS, OK, UNREACHABLE, compensate, compensate_each, rigid_frames
from cellcal.solvers.identification.identify import IdentifyOptions, identify

TOOL_MM = np.array([0.0, 0.0, 100.0])


@pytest.fixture(scope="module")
def cell():
    """ur10e with hidden geometric errors and a hidden joint-2 compliance; calibrated from 250 poses."""
    model = load_robot("ur10e")
    rng = np.random.default_rng(5)
    arm = PhysicalArm(model, rng, [HiddenEffect("joint_compliance", 1, rms_mm=0.5)], target_offsets=[TOOL_MM])
    data = arm.campaign(full_workspace(model, 250, rng))
    finding = analyze(model, data.obs, data.ctx, AnalyzeOptions(causes=("joint_compliance", "backlash")))
    s = finding.extended
    calibrated = from_fit(model, data.obs.target_names, s.x, s.terms, s.theta)
    before = identify(model, data.obs, IdentifyOptions(regularize="none"))  # x_nominal: nominal kinematics, base fitted
    nominal = from_fit(model, data.obs.target_names, before.x_nominal)
    return model, arm, finding, calibrated, nominal, rng


def _in_base(calibrated: CalibratedModel, p_instrument):
    return (p_instrument - calibrated.base[:3]) @ se3.rotvec_to_matrix(calibrated.base[3:])


def test_compensated_targets_land_within_1_2x_of_the_repeatability_floor(cell):
    model, arm, finding, calibrated, nominal, rng = cell
    assert finding.cause == "joint_compliance"
    q_fresh = full_workspace(model, 300, rng)
    desired = arm.true_positions(q_fresh, np.zeros(300, int))  # reachable targets, instrument frame (truth)
    # the program: position targets in each model's base frame, reached on the branch of q_fresh
    comp = compensate(model, calibrated, _in_base(calibrated, desired), None, q_fresh, offset_mm=calibrated.offsets[0])
    plain = compensate(model, nominal, _in_base(nominal, desired), None, q_fresh, offset_mm=nominal.offsets[0])
    ok = (comp.status == OK) & (plain.status == OK)
    assert ok.mean() > 0.85
    noise = rng.normal(scale=arm.repeatability_mm, size=desired.shape)  # the same draws for every way of driving
    floor = np.linalg.norm(noise, axis=1)[ok].mean()  # what the true model would leave

    def error(q):
        return np.linalg.norm(arm.reached(q) + noise - desired, axis=1)[ok].mean()

    driven_nominally = error(plain.q_nominal)  # the controller's own inverse, no correction
    driven_compensated = error(comp.q)
    assert driven_compensated <= 1.2 * floor, (driven_compensated, floor)
    assert driven_nominally > 5.0 * driven_compensated, (driven_nominally, driven_compensated)


def test_batched_solve_matches_the_one_target_loop_and_reaches_the_model_pose(cell):
    model, _, _, calibrated, _, rng = cell
    q0 = full_workspace(model, 12, rng)
    rot, p, _, _ = rigid_frames(model, model.nominal, TOOL_MM)(q0, None)
    batch = compensate(model, calibrated, p, rot, q0, offset_mm=TOOL_MM)
    loop = compensate_each(model, calibrated, p, rot, q0, offset_mm=TOOL_MM)
    assert np.array_equal(batch.status, loop.status)
    assert np.abs(batch.q - loop.q).max() < 1e-9
    ok = batch.status == OK
    r, reached = calibrated.end_frames(batch.q[ok], TOOL_MM)
    assert np.abs(reached - p[ok]).max() < 1e-6
    assert np.abs(se3.matrix_to_rotvec(np.einsum("nij,nkj->nik", rot[ok], r))).max() < 1e-9


def test_rows_out_of_reach_or_limits_are_reported_not_clipped(cell):
    model, _, _, calibrated, _, _ = cell
    q0 = np.deg2rad([[10.0, -80, 90, -100, -90, 0], [10.0, -80, 90, -100, -90, 0], [-20.0, -80, 90, -100, -90, 0]])
    _, p, _, _ = rigid_frames(model, model.nominal, TOOL_MM)(q0, None)
    p[1] = [5000.0, 0.0, 0.0]  # beyond the arm's reach
    limits = np.tile(np.deg2rad([-360.0, 360.0]), (6, 1))
    limits[0, 1] = np.deg2rad(5.0)  # joint 1 may not pass 5 deg: row 0 needs about 10
    out = compensate(replace(model, joint_limits=limits), calibrated, p, None, q0, offset_mm=TOOL_MM)
    assert list(out.status) == [JOINT_LIMITS, UNREACHABLE, OK]
    assert np.rad2deg(out.q[0, 0]) == pytest.approx(10.0, abs=0.5)  # reported, not clipped to the limit


@pytest.fixture(scope="module")
def files(cell, tmp_path_factory):
    model, _, _, calibrated, _, rng = cell
    folder = tmp_path_factory.mktemp("compensate")
    write_calibrated(folder / "cal.yaml", calibrated, "ur10e", {"written_by": "test"})
    q0 = full_workspace(model, 20, rng)
    _, p, _, _ = rigid_frames(model, model.nominal, TOOL_MM)(q0, None)
    p[3] = [4000.0, 0.0, 0.0]
    with open(folder / "targets.csv", "w") as f:
        f.write("name,x_mm,y_mm,z_mm," + ",".join(f"q{j}_deg" for j in range(1, 7)) + "\n")
        for i in range(20):
            f.write(f"t{i}," + ",".join(f"{v:.9f}" for v in [*p[i], *np.rad2deg(q0[i])]) + "\n")
    return folder


def test_cli_writes_corrected_joints_and_cartesian_targets(files, capsys):
    out = files / "out.csv"
    code = main(["compensate", "--robot", str(files / "cal.yaml"), "--targets", str(files / "targets.csv"),
                 "-o", str(out), "--tcp-mm", "0", "0", "100", "--json"])
    captured = capsys.readouterr()
    assert code == 0
    summary = json.loads(captured.out)
    assert summary["rows"] == 20 and summary["frame"] == "base"  # nominal forward kinematics: controller poses
    assert [(r["line"], r["status"]) for r in summary["not_ok"]] == [(5, "unreachable")]
    assert "targets.csv:5: unreachable: out of reach on this branch" in captured.err
    rows = list(csv.DictReader(open(out)))
    assert [r["name"] for r in rows] == [f"t{i}" for i in range(20)]
    assert rows[3]["status"] == "unreachable" and rows[3]["q1_deg"] == ""
    # the input's branch columns are kept beside the solution's, every row's (an unreachable one's too)
    given = list(csv.DictReader(open(files / "targets.csv")))
    assert all(r[f"q{j}_branch_deg"] == g[f"q{j}_deg"] for r, g in zip(rows, given) for j in range(1, 7))
    good = [r for r in rows if r["status"] == "ok"]
    assert len(good) >= 15
    # the corrected Cartesian target differs from the desired one by about what the calibration corrects
    shift = [np.linalg.norm([float(r["x_cmd_mm"]) - float(r["x_mm"]), float(r["y_cmd_mm"]) - float(r["y_mm"]),
                             float(r["z_cmd_mm"]) - float(r["z_mm"])]) for r in good]
    assert 0.05 < np.mean(shift) < 10.0


def test_cli_refuses_unusable_targets_with_one_message(files, tmp_path, capsys):
    bad = tmp_path / "bad.csv"
    bad.write_text("x_mm,y_mm\n1,2\n")
    assert main(["compensate", "--robot", str(files / "cal.yaml"), "--targets", str(bad), "-o",
                 str(tmp_path / "o.csv")]) == 2
    assert "'z_mm'" in capsys.readouterr().err
    bad.write_text("x_mm,y_mm,z_mm\n1,2,3\n")
    assert main(["compensate", "--robot", str(files / "cal.yaml"), "--targets", str(bad), "-o",
                 str(tmp_path / "o.csv")]) == 2
    assert "--seed-deg" in capsys.readouterr().err
    bad.write_text("x_mm,y_mm,z_mm\n1,2,abc\n")
    assert main(["compensate", "--robot", str(files / "cal.yaml"), "--targets", str(bad), "-o",
                 str(tmp_path / "o.csv"), "--seed-deg", "0", "-90", "90", "0", "90", "0"]) == 2
    assert "bad.csv:2: column 'z_mm'" in capsys.readouterr().err
    assert not (tmp_path / "o.csv").exists()


def test_a_nominal_model_of_another_arm_is_refused_and_nothing_written(files, capsys):
    """A UR10e calibration with --nominal ur5e would move every target by the two arms' difference
    (hundreds of mm): refused, status 2, one line; its own nominal (or the same arm named) is accepted."""
    from cellcal.config.model_files import load_calibrated
    from cellcal.config.robot_files import load_robot
    from cellcal.solvers.compensation.compensate import NOMINAL_MISMATCH_MM, nominal_mismatch_mm

    out = files / "other.csv"
    argv = ["compensate", "--robot", str(files / "cal.yaml"), "--targets", str(files / "targets.csv"), "-o", str(out),
            "--tcp-mm", "0", "0", "100"]
    assert main(argv + ["--nominal", "ur5e"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--nominal ur5e: its arm is up to" in err and "started from ur10e" in err, err
    assert not out.exists()
    calibrated = load_calibrated(files / "cal.yaml")
    own = nominal_mismatch_mm(calibrated, load_robot("ur10e"), np.array([0.0, 0.0, 100.0]))
    other = nominal_mismatch_mm(calibrated, load_robot("ur5e"), np.array([0.0, 0.0, 100.0]))
    print(f"calibrated UR10e against its nominal: {own:.2f} mm, against a UR5e: {other:.0f} mm")
    assert own < NOMINAL_MISMATCH_MM / 4 and other > 5 * NOMINAL_MISMATCH_MM  # far apart on both sides
    assert main(argv + ["--nominal", "ur10e"]) == 0  # accepted (the unreachable row 5 is reported by row)
    assert out.exists()


@pytest.mark.parametrize("d", [1, 6, 7, 23])
def test_the_joint_sample_is_scipys_halton_sequence(d):
    """joint_sample's own Halton sequence is scipy.stats.qmc's unscrambled one, point for point (both sum
    the same powers of the bases in the same order: equal to the last bit)."""
    from scipy.stats import qmc

    from cellcal.solvers.compensation.compensate import halton

    assert np.array_equal(halton(1024, d), qmc.Halton(d=d, scramble=False).random(1025)[1:])
