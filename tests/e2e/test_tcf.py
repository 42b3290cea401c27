"""tcf: the tool axis from touches along it, its design check, and the routine end to end,
scored against the simulation's hidden truth."""
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
from support.report_check import assert_report_draws

SIGMA_MM = 0.03 / np.sqrt(3.0)  # per axis, for the sim cell's 0.03 mm repeatability
DRAWN = np.array([0.0, 0.0, 1.0])


def crossing_rows(turns=3, heights=(15.0, 85.0)):
    """Lines, flange rotations, directions and heights of a tcf-like design."""
    down = np.diag([1.0, -1.0, -1.0])
    line, rotations, directions, h = [], [], [], []
    for j in range(turns):
        rotation = se3.rot("z", 2 * np.pi * j / turns) @ down
        for height in heights:
            for k, e in enumerate(np.eye(3)[:2]):
                line.append(2 * j + k)
                rotations.append(rotation)
                directions.append(e)
                h.append(height)
    return np.array(line), np.array(rotations), np.array(directions), np.array(h)


def midpoints(rotations, directions, heights, axis, tip=np.array([0.4, -0.3, 150.0]),
              ball=np.array([-550.0, -400.0, 400.0])):
    """Where each line crosses the axis: e . (ball - R tip + h R axis)."""
    crossing = ball - np.einsum("nij,j->ni", rotations, tip) + heights[:, None] * np.einsum("nij,j->ni", rotations, axis)
    return np.einsum("ni,ni->n", directions, crossing)


def tilted(deg, towards=(1.0, 0.3, 0.0)):
    t = np.asarray(towards) / np.linalg.norm(towards)
    return np.cos(np.deg2rad(deg)) * DRAWN + np.sin(np.deg2rad(deg)) * t


def variant(tmp_path, changes=None, name="c.yaml"):
    return load_cell(edited_cell(tmp_path, "sim", changes, name=name))


# -- the maths ---------------------------------------------------------------------------------------

def test_axis_fit_recovers_a_tilted_axis_exactly_without_noise():
    line, rotations, directions, heights = crossing_rows()
    axis = tilted(0.7)
    fit = pv.fit_axis(line, rotations, directions, heights, midpoints(rotations, directions, heights, axis), DRAWN)
    assert np.degrees(np.arccos(np.clip(fit.axis @ axis, -1, 1))) < 1e-7
    assert np.abs(fit.residuals_mm).max() < 1e-9


def test_axis_design_predicts_the_scatter_of_the_fit():
    line, rotations, directions, heights = crossing_rows()
    axis = tilted(0.5)
    sigma = SIGMA_MM / np.sqrt(2)  # a midpoint of two touches
    design = pv.axis_design(line, rotations, directions, heights, DRAWN, sigma)
    clean = midpoints(rotations, directions, heights, axis)
    rng = np.random.default_rng(4)
    errors = [np.arccos(np.clip(pv.fit_axis(line, rotations, directions, heights,
                                            clean + rng.normal(0, sigma, clean.shape), DRAWN).axis @ axis, -1, 1))
              for _ in range(800)]
    assert float(np.sqrt(np.mean(np.square(errors)))) == pytest.approx(design.expected_error, rel=0.1)
    # 3 turns, 70 mm apart: sqrt(2) sigma / (70 mm sqrt(3))
    assert design.expected_error == pytest.approx(np.sqrt(2) * sigma * np.sqrt(2) / (70.0 * np.sqrt(3)), rel=0.02)


def test_turning_the_tool_keeps_a_slant_of_the_base_out_of_the_axis_and_shows_it():
    """A slant of every crossing fixed in the base frame (a leaning stylus post, the arm's
    own error) does not turn with the tool; a tilt of the tool does. Over turns spread
    evenly round the axis the slant averages out of the axis and stays in the residuals."""
    line, rotations, directions, heights = crossing_rows()
    axis = tilted(0.3)
    slant = 0.004 * heights * directions[:, 0]  # 0.23 deg toward base x, the same at every turn
    fit = pv.fit_axis(line, rotations, directions, heights, midpoints(rotations, directions, heights, axis) + slant,
                      DRAWN)
    assert np.degrees(np.arccos(np.clip(fit.axis @ axis, -1, 1))) < 1e-6
    assert np.sqrt(np.mean(fit.residuals_mm**2)) > 0.05  # far above a midpoint's 0.012 mm: the residual gate fails


# -- the design check -------------------------------------------------------------------------------

def test_heights_too_close_are_refused_before_anything_moves_saying_how_far_apart(tmp_path, capsys):
    cell = variant(tmp_path, {"tcf": {"far_mm": 20}})
    with pytest.raises(PlanRefused) as err:
        runner.prepare("tcf", cell)
    message = str(err.value)
    assert "the heights 15 and 20 mm are 5 mm apart" in message and "for 0.05 deg at 0.03 mm repeatability" in message
    apart = float(re.search(r"at least ([\d.]+) mm apart is needed", message).group(1))
    assert apart == pytest.approx(0.0116 * 70 / 0.05, rel=0.05)
    code, _, stderr = run_cli(capsys, "run", "tcf", "--cell", str(cell.path), "--out", str(tmp_path / "runs"))
    assert code == 2 and "plan refused, nothing moved" in stderr and not (tmp_path / "runs").exists()


# -- end to end --------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def sim_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("tcf")
    code, stdout, _ = run_cli_captured("run", "tcf", "--cell", "sim", "--json", "--out", str(out))
    return code, json.loads(stdout), next(out.glob("tcf-*.csv"))


def test_tcf_finds_the_axis_within_what_the_repeatability_allows(sim_run):
    code, result, dataset = sim_run
    assert code == 0 and result["passed_gates"]
    expected = result["expected_axis_error_deg"]
    assert expected == pytest.approx(0.0116, abs=0.0005)
    assert result["sim_truth"]["axis_error_deg"] <= 3 * expected
    assert result["axis_off_drawing_deg"] == pytest.approx(0.5, abs=3 * expected)  # the sim's runout
    assert result["contact_reach_mm"] == pytest.approx(3.5, abs=0.05)  # shank 3 mm + ball 0.5 mm
    assert {g["name"] for g in result["gates"]} >= {"residual", "conditioning", "identifiability", "contacts",
                                                      "plausibility", "previous"}
    assert len(read_dataset(dataset, "tcf")) == 24


def test_tcf_from_dataset_re_solves_to_the_same_frame(sim_run, capsys):
    _, result, dataset = sim_run
    code, stdout, _ = run_cli(capsys, "run", "tcf", "--cell", "sim", "--json", "--from", str(dataset))
    assert code == 0 and json.loads(stdout)["tool_frame"]["pose_m_rad"] == result["tool_frame"]["pose_m_rad"]


def test_a_stylus_the_search_never_reaches_is_one_error_and_nothing_moves_after(tmp_path):
    cell = load_cell("sim")
    prepared = runner.prepare("tcf", cell)
    with open_drivers(cell) as drivers:
        world = drivers.world
        world.contacts = [dataclasses.replace(c, centre_m=c.centre_m + [0.0, 0.03, 0.0]) for c in world.contacts]
        sent = []
        robot = drivers.robot
        for name in ("move_j", "move_l", "move_until_contact"):
            setattr(robot, name, (lambda f, n: lambda *a: sent.append(n) or f(*a))(getattr(robot, name), name))
        with pytest.raises(RoutineError, match=r"touch side 1 at 15 mm \(turn 1\): the contact search went 8 mm "
                                               r"without touching the stylus"):
            runner.measure(prepared, drivers, tmp_path, lambda message: None)
        assert sent[-1] == "move_until_contact" and sent.count("move_until_contact") == 1  # nothing after it
        np.testing.assert_allclose(robot.tool_frame(), np.zeros(6))  # the controller's tool frame as it was
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2, 3, 4, 5])
def test_tcf_is_within_three_sigma_for_other_cells_and_noise(tmp_path, seed):
    cell = variant(tmp_path, {"sim_truth": {"seed": seed}})
    prepared = runner.prepare("tcf", cell)
    with open_drivers(cell) as drivers:
        drivers.world.rng = np.random.default_rng(100 + seed)
        dataset = runner.measure(prepared, drivers, tmp_path, lambda message: None)
        truth = drivers.world.truth
    result = runner.solve("tcf", cell, dataset)
    assert result.passed_gates
    assert truth.score_tool_frame(result.tool_frame)["axis_error_deg"] <= 3 * result.extra["expected_axis_error_deg"]


@pytest.mark.slow
def test_tcf_axis_then_npoint_gives_the_tcp_without_the_runout_error(tmp_path):
    """tcp-npoint finds the centre of the tip's rounding; with the drawn axis the TCP is off
    by radius x runout (3 mm x 0.5 deg = 0.026 mm); with tcf's axis only by the noise."""
    cell = load_cell("sim")
    with open_drivers(cell) as drivers:
        axis = runner.solve("tcf", cell, runner.measure(runner.prepare("tcf", cell), drivers, tmp_path,
                                                       lambda m: None)).extra["axis"]
    chained = variant(tmp_path, {"tcp_npoint": {"tool_axis": axis}}, name="chained.yaml")
    with open_drivers(chained) as drivers:
        dataset = runner.measure(runner.prepare("tcp-npoint", chained), drivers, tmp_path, lambda m: None)
        truth = drivers.world.truth
    with_axis = runner.solve("tcp-npoint", chained, dataset)
    drawn = runner.solve("tcp-npoint", cell, dataset)
    centre = truth.tool.tcp_m * 1e3 - truth.tool.radius_m * 1e3 * truth.tool.axis
    centre_error = np.linalg.norm(np.asarray(with_axis.extra["tip_centre_mm"]) - centre)
    error = truth.score_tool_frame(with_axis.tool_frame)["position_error_mm"]
    assert abs(error - centre_error) <= 3.0 * np.deg2rad(0.05)  # radius x tcf's axis error
    assert truth.score_tool_frame(with_axis.tool_frame)["axis_error_deg"] < 0.05
    runout = np.linalg.norm(drawn.tool_frame[:3] - with_axis.tool_frame[:3]) * 1e3
    assert runout == pytest.approx(3.0 * np.deg2rad(0.5), abs=3.0 * np.deg2rad(0.05))


def test_the_run_report_draws_the_axis_crossings_against_the_fitted_axis(sim_run, tmp_path):
    _, _, path = sim_run
    result = runner.solve_file("tcf", load_cell("sim"), str(path))
    assert_report_draws(result, tmp_path, "axis crossings along the tool", "the slope is the tilt")
    layers = result.drawing.panels[0].layers
    gaps = np.concatenate([m.xy[:, 1] - f.xy[:, 1] for m, f in zip(layers[::2], layers[1::2])])
    assert np.sqrt(np.mean(gaps**2)) == pytest.approx(result.residual_rms_mm, rel=1e-9)  # the dots off the axis
