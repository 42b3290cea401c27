"""tcp-laser: the fit against the simulation's independent physics, the routine end to end
scored against the hidden truth (several cells, several latencies), the command line, and
the barrier not where the cell file says."""
from __future__ import annotations

import json

import numpy as np
import pytest

from cellcal.config.cells import CellFileError
from cellcal.cli import run as run_cmd
from cellcal.daemon.cells import load_cell, open_drivers
from support.cli_run import run_cli  # tests/support/cli_run.py
from cellcal.routines.framework import runner
from cellcal.routines.framework.records import Dataset
from support.cell_edits import edited_cell  # tests/support/cell_edits.py

POSITION_MM = 0.03  # the targets at 40 mm/s, against the hidden truth
AXIS_DEG = 0.03
CYCLE_S = 30.0


def variant(tmp_path, changes=None, *, name="c.yaml"):
    return edited_cell(tmp_path, "sim", changes, name=name)


def truth_cell(tmp_path, seed, latency_s, repeatability_mm=0.03, jitter_s=0.0005):
    """The sim cell with another hidden truth: seed, latency, noise."""
    return load_cell(variant(tmp_path, {"sim_truth": {"seed": seed, "repeatability_mm": repeatability_mm,
                                                      "trigger_latency_s": latency_s, "trigger_jitter_s": jitter_s}}))


def measured(cell, tmp_path, noise_seed=None):
    """The routine run on the cell; the world's noise reseeded so each case draws its own."""
    prepared = runner.prepare("tcp-laser", cell)
    with open_drivers(cell) as drivers:
        if noise_seed is not None:
            drivers.world.rng = np.random.default_rng(noise_seed)
        dataset = runner.measure(prepared, drivers, tmp_path, lambda message: None)
        truth = drivers.world.truth
    return dataset, truth


# -- the model against the simulation's physics -------------------------------------------------------

def test_without_noise_the_fit_recovers_tool_beams_and_latency_exactly(tmp_path):
    cell = truth_cell(tmp_path, 3, 0.003, repeatability_mm=0.0, jitter_s=0.0)
    dataset, truth = measured(cell, tmp_path)
    result = runner.solve("tcp-laser", cell, dataset)
    score = truth.score_tool_frame(result.tool_frame)
    assert score["position_error_mm"] < 1e-4 and score["axis_error_deg"] < 1e-4, score
    assert result.extra["latency_ms"] == pytest.approx(3.0, abs=1e-4)
    assert result.residual_rms_mm < 1e-5
    for found, real in zip(result.extra["beams"], truth.beams):
        d = real.direction / np.linalg.norm(real.direction)
        off = np.asarray(found["point_mm"]) / 1e3 - real.point_m
        assert np.linalg.norm(off - (off @ d) * d) * 1e3 < 1e-4  # the same line
        assert found["half_width_mm"] == pytest.approx(real.radius_m * 1e3, abs=1e-5)


def test_the_sweeps_back_are_what_measure_the_latency(tmp_path):
    """Refit without the return sweeps and the approaches back up: the latency is then seen
    only through the different directions of the remaining motions, far less sharply."""
    cell = load_cell("sim")
    dataset, _ = measured(cell, tmp_path)
    both = runner.solve("tcp-laser", cell, dataset)
    keep = dataset["direction"] > 0
    one_way = Dataset(dataset.routine, {k: v[keep] for k, v in dataset.columns.items()}, dataset.meta)
    single = runner.solve("tcp-laser", cell, one_way)
    assert single.extra["latency_std_ms"] > 3 * both.extra["latency_std_ms"]


# -- the routine against the hidden truth ----------------------------------------------------------------

@pytest.mark.parametrize("seed, latency_s", [(11, 0.0025), (23, 0.002), (37, 0.003)])
def test_tool_frame_and_latency_against_the_hidden_truth(tmp_path, seed, latency_s):
    cell = truth_cell(tmp_path, seed, latency_s)
    dataset, truth = measured(cell, tmp_path, noise_seed=seed)
    result = runner.solve("tcp-laser", cell, dataset)
    score = truth.score_tool_frame(result.tool_frame)
    assert score["position_error_mm"] <= POSITION_MM, score
    assert score["axis_error_deg"] <= AXIS_DEG, score
    latency_error_ms = abs(result.extra["latency_ms"] - latency_s * 1e3)
    assert latency_error_ms <= 4 * result.extra["latency_std_ms"] and latency_error_ms < 0.5
    assert result.cycle_time_s <= CYCLE_S
    assert result.passed_gates, result.reasons()


@pytest.mark.slow
def test_errors_over_many_cells_stay_within_target_and_within_the_reported_uncertainty(tmp_path):
    errors, z = [], []
    for seed in range(100, 110):
        cell = truth_cell(tmp_path, seed, 0.0025)
        dataset, truth = measured(cell, tmp_path, noise_seed=seed)
        result = runner.solve("tcp-laser", cell, dataset)
        score = truth.score_tool_frame(result.tool_frame)
        errors.append((score["position_error_mm"], score["axis_error_deg"]))
        std = np.array([p.std for p in result.parameters[:3]])
        z.append((result.tool_frame[:3] - truth.tool.tcp_m) * 1e3 / std)
    errors, z = np.array(errors), np.array(z)
    assert errors[:, 0].max() <= POSITION_MM and errors[:, 1].max() <= AXIS_DEG, errors
    assert errors[:, 0].mean() <= 0.02
    assert np.abs(z).max() < 4.0 and 0.5 < np.sqrt(np.mean(z**2)) < 1.5  # the stds are honest


# -- the command line ---------------------------------------------------------------------------------

def test_cellcal_run_writes_back_and_the_dataset_resolves_to_the_same_frame(tmp_path, capsys):
    code, out, _ = run_cli(capsys, "run", "tcp-laser", "--cell", "sim", "--json", "--out", str(tmp_path))
    result = json.loads(out)
    assert code == 0 and result["passed_gates"], result["reasons"]
    assert result["sim_truth"]["position_error_mm"] <= POSITION_MM
    assert result["sim_truth"]["axis_error_deg"] <= AXIS_DEG
    assert result["cycle_time_s"] <= CYCLE_S
    assert 2.0 < result["latency_ms"] < 3.0 and result["latency_std_ms"] < 0.3
    assert any("turn of the tool frame about the tool axis is not measured" in n and "kept from" in n
               for n in result["notes"])
    path = result["dataset"]
    assert path and path.startswith(str(tmp_path))
    code, out, _ = run_cli(capsys, "run", "tcp-laser", "--from", path, "--json")
    again = json.loads(out)
    assert code == 0 and again["dataset"] == path
    np.testing.assert_allclose(again["tool_frame"]["pose_m_rad"], result["tool_frame"]["pose_m_rad"], atol=1e-12)
    assert again["latency_ms"] == pytest.approx(result["latency_ms"], abs=1e-9)


def test_dry_run_plans_and_checks_but_moves_nothing(tmp_path, capsys, monkeypatch):
    def no_drivers(cell):
        raise AssertionError("--dry-run opened the cell's devices")

    monkeypatch.setattr(run_cmd, "open_drivers", no_drivers)
    code, out, _ = run_cli(capsys, "run", "tcp-laser", "--cell", "sim", "--dry-run", "--json", "--out", str(tmp_path))
    summary = json.loads(out)
    assert code == 0 and summary["within_limits"]
    labels = [m["label"] for m in summary["plan"]]
    assert summary["moves"] == len(labels) and sum(label.startswith("sweep") for label in labels) == 16
    assert list(tmp_path.iterdir()) == []


def test_a_barrier_not_where_the_cell_file_says_is_one_clear_error_and_no_dataset(tmp_path, capsys):
    """The beams really 40 mm from where [beams] says: the first measuring motion sees nothing."""
    path = variant(tmp_path, {"sim_truth": {"fixture_error_mm": 40}})
    out_dir = tmp_path / "runs"
    code, out, err = run_cli(capsys, "run", "tcp-laser", "--cell", str(path), "--json", "--out", str(out_dir))
    assert code == 1
    message = json.loads(out)["error"]["message"]
    assert "saw no edge on beam channel" in message and "is the barrier where [beams] says?" in message
    assert err.count("saw no edge") == 1
    assert not out_dir.exists() or list(out_dir.iterdir()) == []


@pytest.mark.parametrize("tcp_laser, key", [
    ({"speed_mm_s": 400}, "speed_mm_s"),
    ({"heights_mm": [12]}, "heights_mm"),
    ({"heights_mm": [12, 150]}, "heights_mm"),
    ({"tilt_deg": 60}, "tilt_deg"),
    ({"sweep_speed": 3}, "sweep_speed"),
])
def test_options_out_of_bounds_are_refused_at_load_naming_the_key(tmp_path, tcp_laser, key):
    with pytest.raises(CellFileError, match=rf"tcp_laser.*{key}"):
        load_cell(variant(tmp_path, {"tcp_laser": tcp_laser}))
