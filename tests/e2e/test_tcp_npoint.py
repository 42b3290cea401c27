"""tcp-npoint: the pivot fit, its design check, the simulated socket, and the routine end
to end, scored against the simulation's hidden truth."""
from __future__ import annotations

import dataclasses
import json
import re

import numpy as np
import pytest

from cellcal.daemon.cells import load_cell, open_drivers
from support.cli_run import run_cli, run_cli_captured  # tests/support/cli_run.py
from cellcal.routines.framework import runner
from cellcal.routines.framework.base import PlanRefused, RoutineError
from cellcal.routines.framework.records import read_dataset
from cellcal.solvers.tool_frames import pivot as pv
from cellcal.solvers.geometry import se3
from support.cell_edits import edited_cell  # tests/support/cell_edits.py
from support.report_check import assert_report_draws, layer
from support.routine_checks import RecordingRobot  # tests/support/routine_checks.py

SIGMA_MM = 0.03 / np.sqrt(3.0)  # per axis, for the sim cell's 0.03 mm repeatability


def random_rotations(rng, n, spread_deg=30.0):
    down = np.diag([1.0, -1.0, -1.0])
    tilt = rng.normal(size=(n, 3)) * np.deg2rad(spread_deg) / np.sqrt(3)
    return np.einsum("nij,jk->nik", se3.rotvec_to_matrix(tilt), down)


def seated_flanges(rotations, tool_point, pivot_point):
    return pivot_point - np.einsum("nij,j->ni", rotations, tool_point)


def variant(tmp_path, changes=None, name="c.yaml"):
    return load_cell(edited_cell(tmp_path, "sim", changes, name=name))


# -- the maths ---------------------------------------------------------------------------------------

def test_pivot_fit_recovers_tool_and_pivot_exactly_without_noise():
    rng = np.random.default_rng(1)
    rotations = random_rotations(rng, 6)
    t, c = np.array([1.2, -0.7, 146.0]), np.array([-800.0, 50.0, 403.0])
    fit = pv.fit_pivot(rotations, seated_flanges(rotations, t, c), noise_floor=SIGMA_MM)
    np.testing.assert_allclose(fit.tool_point, t, atol=1e-9)
    np.testing.assert_allclose(fit.pivot_point, c, atol=1e-9)
    assert fit.rejected == [] and fit.kept.all()


def test_pivot_design_predicts_the_scatter_of_the_fit():
    """The expected error the plan is judged by is the RMS error the fit really has."""
    rng = np.random.default_rng(2)
    rotations = random_rotations(rng, 8)
    t, c = np.array([0.0, 0.0, 146.0]), np.array([-800.0, 50.0, 403.0])
    design = pv.pivot_design(rotations, SIGMA_MM)
    clean = seated_flanges(rotations, t, c)
    errors = [pv.fit_pivot(rotations, clean + rng.normal(0, SIGMA_MM, clean.shape), noise_floor=SIGMA_MM,
                           k=1e9).tool_point - t for _ in range(600)]
    rms = float(np.sqrt(np.mean(np.sum(np.square(errors), axis=1))))
    assert rms == pytest.approx(design.expected_error, rel=0.1)
    assert design.condition < 20


def test_pivot_fit_rejects_one_bad_seat_and_names_it():
    rng = np.random.default_rng(3)
    rotations = random_rotations(rng, 8)
    t, c = np.array([0.3, 0.2, 146.0]), np.array([-800.0, 50.0, 403.0])
    flanges = seated_flanges(rotations, t, c) + rng.normal(0, SIGMA_MM, (8, 3))
    flanges[5] += [0.25, -0.1, 0.0]  # swarf under the tip at one seat
    fit = pv.fit_pivot(rotations, flanges, noise_floor=SIGMA_MM)
    assert fit.rejected == [5] and not fit.kept[5] and fit.kept.sum() == 7
    assert np.linalg.norm(fit.tool_point - t) < 0.05
    clean = pv.fit_pivot(np.delete(rotations, 5, axis=0), np.delete(flanges, 5, axis=0), noise_floor=SIGMA_MM)
    np.testing.assert_allclose(fit.tool_point, clean.tool_point, atol=1e-12)


# -- the design check before anything moves ---------------------------------------------------------

def test_too_little_spread_is_refused_before_anything_moves_saying_how_much_is_needed(tmp_path, capsys):
    cell = variant(tmp_path, {"tcp_npoint": {"spread_deg": 4}})
    with pytest.raises(PlanRefused) as err:
        runner.prepare("tcp-npoint", cell)
    message = str(err.value)
    assert "the 8 orientations spread +-4.0 deg about the pivot" in message
    assert "for 0.05 mm at 0.03 mm repeatability" in message
    need = float(re.search(r"at least ([\d.]+) deg is needed", message).group(1))
    routine = runner.routine_class("tcp-npoint")(cell, runner.read_options("tcp-npoint", cell))
    assert routine.design(4.0).expected_error > 0.05
    assert routine.design(need).expected_error == pytest.approx(0.05, abs=0.001)
    assert 4.0 < need < 30.0
    out = tmp_path / "runs"
    code, stdout, stderr = run_cli(capsys, "run", "tcp-npoint", "--cell", str(cell.path), "--out", str(out))
    assert code == 2 and "plan refused, nothing moved" in stderr and "at least" in stderr
    assert not out.exists()


# -- the simulated pivot --------------------------------------------------------------------------------

def test_the_sim_socket_seats_a_tilted_tip_and_the_joints_are_off_by_the_arm_repeatability():
    cell = load_cell("sim")
    prepared = runner.prepare("tcp-npoint", cell)
    approach, search = prepared.plan[1], prepared.plan[2]  # seat 1, tilted 30 deg
    with open_drivers(cell) as drivers:
        world, robot = drivers.world, drivers.robot
        robot.set_tcp(cell.tool.tcp_pose)
        robot.move_j(prepared.plan[0].q_rad, 1.0, 2.0)
        robot.move_l(approach.pose, 0.1, 1.0)
        found = robot.move_until_contact(search.direction * search.speed, search.travel_m / search.speed)
        assert found.contact
        np.testing.assert_allclose(world.tool_body()[0], world.pivot.seat_m, atol=1e-12)  # the real tip sits
        rotation, position = world.physics.flange(world.q)  # where the joints put it, without the scatter
        off = world.pivot.seat_m - world.truth.tool.segment(rotation, position)[0]
        assert 0 < np.linalg.norm(off) < 4 * np.sqrt(3) * SIGMA_MM / 1e3
        np.testing.assert_allclose(off, world._repeat_offset_m, atol=1e-12)
        assert world.pivot.touch(world.pivot.seat_m + [0.0, 0.0, 0.01], 0.003) is None
        assert world.pivot.touch(world.pivot.seat_m + [0.002, 0.0, 0.0], 0.003) == "seat"
        assert world.pivot.touch(world.pivot.seat_m + [0.008, 0.0, 0.0027], 0.003) == "face"


# -- end to end --------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def sim_run(tmp_path_factory):
    """One run on the shipped sim cell through the command line: exit code, JSON, dataset."""
    out = tmp_path_factory.mktemp("npoint")
    code, stdout, _ = run_cli_captured("run", "tcp-npoint", "--cell", "sim", "--json", "--out", str(out))
    return code, json.loads(stdout), next(out.glob("tcp-npoint-*.csv"))


def test_npoint_finds_the_tcp_within_0_05_mm_of_the_hidden_truth(sim_run):
    code, result, dataset = sim_run
    assert code == 0 and result["passed_gates"] and result["reasons"] == []
    assert result["sim_truth"]["position_error_mm"] <= 0.05
    assert result["expected_tcp_error_mm"] < 0.02 and result["design_condition"] < 10
    assert result["rejected_seats"] == [] and result["n_measurements"] == 8
    assert {g["name"] for g in result["gates"]} >= {"residual", "conditioning", "identifiability", "seating",
                                                      "plausibility", "previous"}
    assert result["residual_rms_mm"] <= 3 * result["expected_noise_mm"]
    assert result["dataset"] == str(dataset)
    data = read_dataset(dataset, "tcp-npoint")
    assert len(data) == 8 and data.complete and data.meta["cycle_time_s"] > 0


def test_from_dataset_re_solves_to_the_same_frame(sim_run, capsys):
    _, result, dataset = sim_run
    code, stdout, _ = run_cli(capsys, "run", "tcp-npoint", "--cell", "sim", "--json", "--from", str(dataset))
    again = json.loads(stdout)
    assert code == 0 and again["tool_frame"]["pose_m_rad"] == result["tool_frame"]["pose_m_rad"]
    assert again["sim_truth"] == result["sim_truth"]


def test_dry_run_plans_every_seat_and_moves_nothing(capsys, tmp_path):
    code, stdout, _ = run_cli(capsys, "run", "tcp-npoint", "--cell", "sim", "--dry-run", "--json",
                              "--out", str(tmp_path))
    summary = json.loads(stdout)
    assert code == 0 and summary["within_limits"] and summary["moves"] == 27
    assert [m["kind"] for m in summary["plan"]].count("contact") == 8
    assert list(tmp_path.iterdir()) == []


def test_an_injected_bad_seat_in_the_dataset_is_rejected_and_named(sim_run, tmp_path):
    data = read_dataset(sim_run[2], "tcp-npoint")
    data.columns["q1_rad"] = data["q1_rad"].copy()
    data.columns["q1_rad"][4] += 0.001  # seat 5 recorded ~0.8 mm off: it did not sit right
    cell = load_cell("sim")
    result = runner.solve_file("tcp-npoint", cell, data.write(tmp_path / "bad.csv"))
    assert result.extra["rejected_seats"] == [5]
    assert any(n.startswith("seat 5 ") and "rejected" in n for n in result.notes)
    assert result.passed_gates and len(result.residuals_mm) == 7
    with open_drivers(cell) as drivers:
        truth = drivers.world.truth
    assert truth.score_tool_frame(result.tool_frame)["position_error_mm"] <= 0.05


def test_a_fouled_seat_in_the_sim_is_rejected_and_named(tmp_path):
    cell = load_cell("sim")
    prepared = runner.prepare("tcp-npoint", cell)
    with open_drivers(cell) as drivers:
        for offset in ([0.0] * 3, [0.0] * 3, [0.0003, 0.0, 0.0]):  # swarf in the socket at seat 3
            drivers.world.foul_pivot(offset)
        dataset = runner.measure(prepared, drivers, tmp_path, lambda message: None)
        truth = drivers.world.truth
    result = runner.solve("tcp-npoint", cell, dataset)
    assert result.extra["rejected_seats"] == [3]
    assert result.extra["seat_residuals_mm"][2] == pytest.approx(0.3, abs=0.05)
    assert result.passed_gates
    assert truth.score_tool_frame(result.tool_frame)["position_error_mm"] <= 0.05


def test_a_pivot_the_search_never_reaches_is_one_error_and_nothing_moves_after(tmp_path):
    cell = load_cell("sim")
    prepared = runner.prepare("tcp-npoint", cell)
    with open_drivers(cell) as drivers:
        world = drivers.world
        world.pivot = dataclasses.replace(world.pivot, point_m=world.pivot.point_m + [0.0, 0.0, -0.02])
        drivers.robot = RecordingRobot(drivers.robot)
        with pytest.raises(RoutineError, match=r"seat 1: the contact search along the tool axis went 10 mm without "
                                               r"touching the pivot: is \[pivot\] point_m"):
            runner.measure(prepared, drivers, tmp_path, lambda message: None)
        assert [kind for kind, *_ in drivers.robot.commands] == ["joint", "linear", "contact"]
        np.testing.assert_allclose(drivers.robot.tool_frame(), np.zeros(6))  # the controller's tool frame as it was
    assert list(tmp_path.iterdir()) == []


def test_cli_reports_an_unreachable_pivot_with_one_message_and_no_dataset(tmp_path, capsys):
    # seed 6 puts the real pivot 40 mm to the side of where the file says: beyond the fixture
    cell = variant(tmp_path, {"sim_truth": {"seed": 6, "fixture_error_mm": 40}})
    with open_drivers(cell) as drivers:
        off = (drivers.world.truth.pivot_m - cell.pivot_m) * 1e3
    assert np.hypot(off[0], off[1]) > 30
    out = tmp_path / "runs"
    code, stdout, stderr = run_cli(capsys, "run", "tcp-npoint", "--cell", str(cell.path), "--json", "--out", str(out))
    assert code == 1 and "without touching the pivot" in json.loads(stdout)["error"]["message"]
    assert stderr.count("seat 1: the contact search") == 1
    assert not out.exists() or not list(out.iterdir())


@pytest.mark.slow
def test_a_tip_landing_beside_the_socket_fails_the_residual_gate(tmp_path):
    """6 mm off: outside the socket's 4 mm rim, every tip lands on the flat beside it."""
    cell = load_cell("sim")
    prepared = runner.prepare("tcp-npoint", cell)
    with open_drivers(cell) as drivers:
        world = drivers.world
        world.pivot = dataclasses.replace(world.pivot, point_m=world.pivot.point_m + [0.006, 0.0, 0.0])
        dataset = runner.measure(prepared, drivers, tmp_path, lambda message: None)
    result = runner.solve("tcp-npoint", cell, dataset)
    assert not result.passed_gates
    assert [g.name for g in result.gates if not g.passed] == ["residual"]
    assert result.residual_rms_mm > 0.1
    assert any("did not seat" in n for n in result.notes)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2, 3, 4, 5])
def test_npoint_is_within_0_05_mm_for_other_cells_and_noise(tmp_path, seed):
    cell = variant(tmp_path, {"sim_truth": {"seed": seed}})
    prepared = runner.prepare("tcp-npoint", cell)
    with open_drivers(cell) as drivers:
        drivers.world.rng = np.random.default_rng(100 + seed)  # the arm's scatter differs too
        dataset = runner.measure(prepared, drivers, tmp_path, lambda message: None)
        truth = drivers.world.truth
    result = runner.solve("tcp-npoint", cell, dataset)
    assert result.passed_gates
    assert truth.score_tool_frame(result.tool_frame)["position_error_mm"] <= 0.05
    centre = truth.tool.tcp_m * 1e3 - truth.tool.radius_m * 1e3 * truth.tool.axis
    assert np.linalg.norm(np.asarray(result.extra["tip_centre_mm"]) - centre) <= 3 * result.extra["expected_tcp_error_mm"]


def test_the_run_report_draws_the_seats_about_the_fitted_pivot(sim_run, tmp_path):
    _, doc, path = sim_run
    result = runner.solve_file("tcp-npoint", load_cell("sim"), str(path))
    assert_report_draws(result, tmp_path, "flange about the pivot, from above", "tip centre about the fitted pivot")
    tips = layer(result, "tip centre about the fitted pivot, from above", "seats")
    flange = layer(result, "flange about the pivot, from the side", "seats")
    reach = np.linalg.norm(np.array([doc["tool_frame"][k] for k in ("x_mm", "y_mm", "z_mm")]))
    assert np.sqrt(np.mean(np.sum(tips**2, axis=1))) <= result.residual_rms_mm + 1e-12  # x, y of the residuals
    assert np.linalg.norm(flange, axis=1).max() <= reach + 1.0  # within the sphere of the tool's reach
