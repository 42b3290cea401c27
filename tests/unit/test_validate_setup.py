"""Validation rows of the same setup or of another one: ``analyze --validate B --same-setup`` scores B with the
frame and target offsets fitted on A (nothing fitted on B), the default fits B's own; ``identify --validate``
the other way round (``--new-setup`` fits B's own). The JSON says which was used."""
from __future__ import annotations

import json

import numpy as np
import yaml
import pytest

from cellcal.cli.analyze import _context
from cellcal.config.robot_files import load_robot
from cellcal.measurements.reader import read_measurements
from cellcal.measurements.writer import write_measurements
from cellcal.sims.physics.physical_arm import HiddenEffect
from cellcal.sims.physics.workspace import full_workspace
from cellcal.solvers.analysis.analyze import AnalyzeOptions, analyze
from cellcal.solvers.analysis.transfer import transfer
from cellcal.solvers.identification.measurement_model import Layout, predict
from support.cli_run import refused, run_cli  # tests/support/cli_run.py
from support.hidden_cases import make_case  # tests/support/hidden_cases.py

ROBOT = "ur5e"
N_A, N_B = 200, 20  # a test set of 20 poses: what a published test set of a session holds


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """A campaign with a hidden cyclic error (A) and a test set of the same session (B: the same robot,
    instrument frame and target, other poses)."""
    model = load_robot(ROBOT)
    case = make_case(model, [HiddenEffect("cyclic_joint_error", 1, order=2, phase_rad=0.7)], [4.0], n=N_A, seed=3)
    test_set = case.arm.campaign(full_workspace(model, N_B, np.random.default_rng(77)))
    folder = tmp_path_factory.mktemp("setup")
    for name, obs in (("a.csv", case.campaign.obs), ("b.csv", test_set.obs)):
        write_measurements(folder / name, q_rad=obs.q, xyz_mm=obs.xyz_mm)
    return model, folder


def _json(capsys, *argv):
    code, out, err = run_cli(capsys, *argv, "--json")
    assert code == 0, err
    return json.loads(out)


def test_analyze_scores_a_test_set_of_the_same_setup_with_nothing_fitted_on_it(session, capsys):
    model, folder = session
    a, b = str(folder / "a.csv"), str(folder / "b.csv")
    same = _json(capsys, "analyze", "--robot", ROBOT, "--data", a, "--validate", b, "--same-setup")["validate"]
    new = _json(capsys, "analyze", "--robot", ROBOT, "--data", a, "--validate", b)["validate"]
    assert (same["setup"], new["setup"]) == ("same", "new")
    # nothing fitted on B: the geometric fit of A, its frame and target offset as fitted there, predicts B
    table, test = read_measurements(a, 6), read_measurements(b, 6)
    obs, obs_b = table.observations(), test.observations()
    finding = analyze(model, obs, _context(table), AnalyzeOptions())
    as_fitted = np.linalg.norm(predict(Layout(model, obs.target_names), finding.baseline.x, obs_b) - obs_b.xyz_mm, axis=1)
    # the same numbers through the same arithmetic: 1e-9 relative leaves room for the order of the sums only
    assert same["baseline_mean_mm"] == pytest.approx(as_fitted.mean(), rel=1e-9)
    assert same["effect"] == finding.extended.label and same["gain_pct"] > 0  # the effect holds on B
    # the refit of B's frame and target offset (9 parameters on 60 coordinates) lowers B's sum of squares: it
    # is the least-squares minimum over them, and A's values are one of the choices it had
    runs = {s: transfer(model, finding, obs, obs_b, _context(test), same_setup=s) for s in (True, False)}
    rms = {s: np.sqrt(np.mean(runs[s].baseline_errors_mm ** 2)) for s in runs}
    assert rms[False] <= rms[True] * (1 + 1e-9), rms
    assert new["baseline_mean_mm"] == pytest.approx(runs[False].baseline_mean_mm, rel=1e-9)


def test_identify_fits_the_validation_rows_own_frame_only_when_told_they_are_another_setup(session, capsys):
    folder = session[1]
    a, b = str(folder / "a.csv"), str(folder / "b.csv")
    default = _json(capsys, "identify", "--robot", ROBOT, "--data", a, "--validate", b)
    same = _json(capsys, "identify", "--robot", ROBOT, "--data", a, "--validate", b, "--same-setup")
    new = _json(capsys, "identify", "--robot", ROBOT, "--data", a, "--validate", b, "--new-setup")
    assert default["validate"] == same["validate"] and same["validate"]["setup"] == "same"
    assert new["validate"]["setup"] == "new"
    # B's own frame and offset are the least-squares minimum of B's errors: its rms is at most the calibration's
    assert new["validate"]["rms_mm"] <= same["validate"]["rms_mm"] * (1 + 1e-9), (new["validate"], same["validate"])
    assert new["before"]["validate_mean_mm"] != same["before"]["validate_mean_mm"]  # the nominal model refit too
    # a model file written with either records the held-out error that run printed, and how it was scored
    for flag, printed in (("--same-setup", same), ("--new-setup", new)):
        path = folder / f"model{flag}.yaml"
        _json(capsys, "identify", "--robot", ROBOT, "--data", a, "--validate", b, flag, "--write-model", str(path))
        heldout = yaml.safe_load(path.read_text())["calibration"]["heldout"]
        assert heldout["mean_mm"] == pytest.approx(printed["validate"]["mean_mm"], rel=1e-9), flag
        assert ("another setup" in heldout["how"]) == (flag == "--new-setup"), heldout["how"]


@pytest.mark.parametrize("argv, words", [
    (["analyze", "--same-setup"], ["--same-setup: says how --validate's data set is scored; give --validate"]),
    (["analyze", "--new-setup"], ["--new-setup: says how --validate's data set is scored"]),
    (["identify", "--new-setup"], ["--new-setup: says how validation rows are scored; give --validate"]),
    (["analyze", "--validate", "{b}", "--same-setup", "--new-setup"], ["not allowed with argument"]),
])
def test_a_setup_option_without_its_validation_is_one_message(session, capsys, argv, words):
    folder = session[1]
    command, *rest = argv
    refused(capsys, [command, "--robot", ROBOT, "--data", folder / "a.csv",
                     *(r.format(b=folder / "b.csv") for r in rest)], 2, words)


def test_a_same_setup_validation_with_a_target_the_calibration_never_measured_is_refused(session, capsys, tmp_path):
    folder = session[1]
    test = read_measurements(folder / "b.csv", 6)
    write_measurements(tmp_path / "other.csv", q_rad=test.q_rad, xyz_mm=test.xyz_mm, target_names=("smr9",),
                       target=np.zeros(len(test.q_rad), int))
    refused(capsys, ["analyze", "--robot", ROBOT, "--data", folder / "a.csv", "--validate", tmp_path / "other.csv",
                     "--same-setup"], 2, ["--same-setup:", "measures target(s) smr9"])
