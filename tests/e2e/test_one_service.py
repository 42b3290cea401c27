"""One service per store, per panel and per robot, end to end on the networked simulated cell.

``cellcal daemon`` runs as a process on sim-net's fakes (tests/support/daemon_harness.py); a second
daemon, ``cellcal tool rollback`` and ``cellcal run`` are started beside it as an operator
would, and must be refused at once with one line naming the process that holds what they
need (exit status 1), changing nothing: the first daemon's run goes on to its end, the
controller keeps its tool frame, the arm does not move.
"""
from __future__ import annotations

import subprocess
import sys
import time

import numpy as np
import pytest

from support.cell_edits import edited_cell
from cellcal.daemon.service import ResultCode
from cellcal.daemon.store import Store
from support.daemon_harness import press_start, until_the_run_ends

# A refused command touches no device: it ends in well under a second of its own; the bound
# allows for starting a Python process with numpy on a loaded 2-core machine.
REFUSED_WITHIN_S = 20.0


def cellcal(*argv: str) -> subprocess.CompletedProcess:
    t0 = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "cellcal.cli.main", *argv], capture_output=True, text=True,
                          timeout=REFUSED_WITHIN_S)
    done.seconds = time.monotonic() - t0
    return done


def refusal(done: subprocess.CompletedProcess) -> str:
    """The one line a refused command prints; status 1, stdout empty, no traceback."""
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert done.returncode == 1 and done.stdout == "" and len(lines) == 1, (done.returncode, done.stdout,
                                                                           done.stderr)
    assert lines[0].startswith("cellcal: in use: ") and lines[0].endswith("nothing was changed"), lines[0]
    return lines[0]


def holder(daemon) -> str:
    return f"the cellcal service (pid {daemon.proc.pid}: "


@pytest.mark.slow
def test_a_second_daemon_on_the_same_store_is_refused_and_the_live_run_goes_on_to_its_end(cell_net,
                                                                                         cellcal_daemon):
    net = cell_net
    daemon = cellcal_daemon(net)
    counter = net.panel.run_counter()
    press_start(net, "tcp-laser")  # returns once the arm moves: the run is live
    second = cellcal("daemon", "--cell", str(net.path), "--state-dir", str(daemon.state_dir), "--poll-s", "0.02")
    line = refusal(second)
    assert holder(daemon) in line and f"holds the state folder {daemon.state_dir}" in line, line
    assert "systemctl stop cellcal" in line
    # The first's run goes on: it ends as its own gates decide (checked on the store below). Not
    # asserted from the arm's "moving" flag here: between two sweeps and while it solves the
    # arm stands still, so a snapshot of the flag says nothing about the run.
    until_the_run_ends(net, counter)
    assert daemon.proc.poll() is None, daemon.log()  # the first daemon serves on
    store = Store.open(daemon.state_dir, create=False)
    try:
        run = store.run(1)
        trail = [s for _, s, _ in store.states(1)]
    finally:
        store.close()
    # the run ended as the first daemon ended it (its gates decide done or refused), never interrupted
    assert run.result_code != ResultCode.INTERRUPTED and "interrupted" not in trail, trail
    assert trail[-1] == run.state and run.finished_at is not None
    assert (daemon.state_dir / "cellcal.lock").read_text() == f"{daemon.proc.pid}\n"


@pytest.mark.parametrize("shared", ["panel", "robot"])
def test_a_second_daemon_on_another_store_and_cell_file_sharing_a_device_is_refused(cell_net, cellcal_daemon,
                                                                                   loopback, tmp_path, shared):
    net = cell_net
    daemon = cellcal_daemon(net)
    elsewhere = loopback()  # an address no fake listens on: the refusal comes before any connection
    if shared == "panel":  # another robot, the same Modbus panel (host, port, unit id)
        change, label = {"drivers": {"robot": {"host": elsewhere}}}, f"panel {net.host}:5020 unit 1"
    else:  # the same robot, another panel
        change, label = {"drivers": {"panel": {"host": elsewhere}}}, f"robot {net.host}"
    other = edited_cell(tmp_path, net.path, change, name="other-cell.yaml")
    second = cellcal("daemon", "--cell", str(other), "--state-dir", str(tmp_path / "other-state"))
    line = refusal(second)
    assert holder(daemon) in line and f"holds {label};" in line, line
    assert not (tmp_path / "other-state" / "cellcal.db").exists()  # refused before its store was made
    assert daemon.proc.poll() is None, daemon.log()


def test_rollback_and_run_while_the_service_holds_the_robot_say_so_and_change_nothing(cell_net, cellcal_daemon,
                                                                                     tmp_path):
    net = cell_net
    daemon = cellcal_daemon(net)
    # a store with a write-back of this cell's robot to roll back (the service's own is empty yet)
    records = tmp_path / "records"
    store = Store.open(records)
    run = store.begin_run("tcp-npoint", str(net.path))
    store.finish_run(run, "done", 0, "written back")
    store.record_tool_frame(run, "write", net.cell.tool.tcp_pose, net.previous)
    store.close()
    before = net.state()

    rollback = cellcal("tool", "rollback", "--cell", str(net.path), "--state-dir", str(records))
    line = refusal(rollback)
    assert line.startswith(f"cellcal: in use: {holder(daemon)}") and f"holds robot {net.host};" in line, line
    assert "stop it first (systemctl stop cellcal" in line

    measure = cellcal("run", "tcp-npoint", "--cell", str(net.path), "--out", str(tmp_path / "runs"), "--json")
    assert measure.returncode == 1 and holder(daemon) in measure.stderr, measure.stderr
    assert measure.stdout.strip().startswith('{"error": {"code": 1, "message": "in use: ')  # --json: the object

    after = net.state()
    np.testing.assert_array_equal(after["tcp_offset"], before["tcp_offset"])  # the frame as it was
    np.testing.assert_array_equal(after["q"], before["q"])  # nothing moved
    assert not list(tmp_path.glob("runs/**/*.csv"))  # no dataset begun (the folder may be made, checked early)
    store = Store.open(records, create=False)
    try:
        assert [f["action"] for f in store.tool_frames()] == ["write"]  # no rollback recorded
    finally:
        store.close()
    assert daemon.proc.poll() is None, daemon.log()
