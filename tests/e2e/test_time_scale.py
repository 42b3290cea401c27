"""The networked simulated cell on a faster clock measures what it measures in real time.

tcp-laser, tcp-check and the tracker campaign run through the network fakes (``cellcal run``
against :class:`~cellcal.sims.net.cell.SimCell`) at K = 1 (real time) and at the suite's K
(tests/support/daemon_harness.py SUITE_TIME_SCALE), on one cell file and one seed. Every
timestamp the fakes report is simulated time, so at both scales the plan is the same, the
barrier switches as often, the trigger latency the routine fits on the controller's clock
is the same within its noise, and both results are within the routine's accuracy target of
the hidden truth. The sections are short (the K = 1 runs take the arm's real time).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from support.cell_edits import edited_cell, replaced  # tests/support/cell_edits.py
from support.cli_run import run_cli  # tests/support/cli_run.py
from support.daemon_harness import SUITE_TIME_SCALE
from test_tracker_routine import floor_bound  # tests/e2e/test_tracker_routine.py: the campaign's target

pytestmark = pytest.mark.slow

SECTIONS = {  # tcp-laser as shipped; tcp-check on [beams] as installed (said so: the tip not determined); a
    "tcp-laser": {},  # short tracker campaign
    "tcp-check": {"tcp_check": {"beam_std_mm": 0.5}},
    "tracker": {"tracker": replaced({"target": "smr1", "instrument_m": [-2.5, 0.0, 1.0], "poses": 10,
                                     "validation_poses": 3, "candidates": 80, "settle_s": 0, "measure_s": 0}),
                # twice the shipped joint speed: the real-time run's arm time halved, the plan the same at both K
                "limits": {"joint_speed_rad_s": 3.0, "joint_accel_rad_s2": 8.0}},
}
# the routines' accuracy targets against the hidden truth (tests/e2e/test_sim_cells.py, the Modbus ring)
TCP_TARGET_MM, AXIS_TARGET_DEG = 0.03, 0.03
# what the controller's clock measures differently at another scale: the wall time the product spends
# between moves (its calls, the stream catching up) passes K times as much simulated time
RUN_DEPENDENT = ("cycle_time_s", "motion_s", "tool_frame_before")


def run_at(tmp_path, capsys, loopback, routine: str, time_scale: float) -> tuple[dict, dict]:
    """`cellcal run ROUTINE --json` through sim-net's fakes on a clock `time_scale` times the wall's:
    the result and its dataset's meta (the plan as measured)."""
    from cellcal.daemon.cells import load_cell
    from cellcal.sims.net.cell import SimCell

    folder = tmp_path / f"k{time_scale:g}"
    folder.mkdir()
    path = edited_cell(folder, "sim-net", SECTIONS[routine], name="cell.yaml", host=loopback())
    with SimCell(load_cell(path), time_scale=time_scale):
        code, out, err = run_cli(capsys, "run", routine, "--cell", str(path), "--json", "--out", str(folder))
    assert code == 0, f"K = {time_scale:g}: {out}{err[-2000:]}"
    result = json.loads(out)
    meta = next(json.loads(line.removeprefix("# meta: ")) for line in Path(result["dataset"]).read_text().splitlines()
                if line.startswith("# meta: "))
    return result, meta


@pytest.mark.parametrize("routine", ["tcp-laser", "tcp-check"])
def test_the_barrier_routines_measure_the_same_at_the_suites_clock_as_in_real_time(tmp_path, capsys, loopback,
                                                                                   routine):
    (real, real_meta), (fast, fast_meta) = (run_at(tmp_path, capsys, loopback, routine, k)
                                            for k in (1.0, SUITE_TIME_SCALE))
    print(f"{routine}: cycle {real['cycle_time_s']:.2f} / {fast['cycle_time_s']:.2f} s, latency "
          f"{real['latency_ms']:.3f} +- {real['latency_std_ms']:.3f} / {fast['latency_ms']:.3f} +- "
          f"{fast['latency_std_ms']:.3f} ms, truth {real['sim_truth']}, {fast['sim_truth']}")
    assert {k: v for k, v in real_meta.items() if k not in RUN_DEPENDENT} == \
        {k: v for k, v in fast_meta.items() if k not in RUN_DEPENDENT}  # the same plan
    # the same sweeps over the same beams: every crossing switches the barrier at both scales
    assert real["n_edges"] == fast["n_edges"] and real["n_measurements"] == fast["n_measurements"]
    for result in (real, fast):
        truth = result["sim_truth"]
        assert result["passed_gates"] and truth["axis_error_deg"] <= AXIS_TARGET_DEG, truth
        if "tip" in truth["determined"]:
            assert truth["position_error_mm"] <= TCP_TARGET_MM, truth
    assert real.get("verdict") == fast.get("verdict")
    # the latency is fitted on the controller's clock from edges stamped on it: two independent estimates
    # of one latency, each with its own standard deviation; 3 sigma of their difference is a false alarm
    # in 0.3 % of runs, while a clock that mixed wall and simulated time would shift it by (K-1) x 2.5 ms
    spread_ms = 3.0 * float(np.hypot(real["latency_std_ms"], fast["latency_std_ms"]))
    assert abs(real["latency_ms"] - fast["latency_ms"]) <= spread_ms, (real["latency_ms"], fast["latency_ms"])


def test_the_tracker_campaign_measures_the_same_at_the_suites_clock_as_in_real_time(tmp_path, capsys, loopback):
    (real, real_meta), (fast, fast_meta) = (run_at(tmp_path, capsys, loopback, "tracker", k)
                                            for k in (1.0, SUITE_TIME_SCALE))
    print(f"tracker: campaign {real['campaign_time_s']:.2f} / {fast['campaign_time_s']:.2f} s, validation over "
          f"floor {real['sim_truth']['validation_over_floor']:.3f} / {fast['sim_truth']['validation_over_floor']:.3f}")
    assert real_meta["plan_id"] == fast_meta["plan_id"] and real["n_measurements"] == fast["n_measurements"]
    n_cal = SECTIONS["tracker"]["tracker"].value["poses"]
    for result in (real, fast):  # the module's target: the held-out mean near the floor the true model leaves
        allowed = floor_bound(1.0, len(result["parameters"]), n_cal)
        assert result["passed_gates"] and result["sim_truth"]["validation_over_floor"] <= allowed, result["sim_truth"]
