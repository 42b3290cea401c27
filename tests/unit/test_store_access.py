"""Who may make, write and hold the results store, and what ``tool rollback`` puts back where.

- the commands that read the store (``runs list|show``, ``tool history|rollback``) never make
  a store or a folder: a typo in ``--state-dir`` is one message, status 2;
- ``cellcal daemon`` checks at start that it can write its folder and the store's files
  (a store made by another user, root say, is named with its owner and the command that
  fixes it), before it takes anything;
- the claims of daemon/claims.py: the state folder's lock and a device's claim name the
  process that holds them, and are free again once given back;
- a rollback goes only to the robot of the run's cell, and repeated rollbacks walk back
  through the history.

Each case runs the real command line in process and asserts the status, one message naming
what is wrong, no traceback, and that nothing was made or changed.
"""
from __future__ import annotations

import json
import os
import shutil
import stat
import tempfile
from pathlib import Path

import numpy as np
import pytest

from cellcal.config.cell_files import shipped_cells
from cellcal.daemon.claims import Device, DeviceClaim, FolderLock, InUseError, devices
from cellcal.daemon.cells import load_cell
from cellcal.daemon.store import Store, StoreError, check_state_folder
from support.users import NOBODY, as_nobody
from support.cli_run import one_message, run_cli  # tests/support/cli_run.py



# -- the commands that read the store never make one -----------------------------------------------

READERS = {
    "runs list": ["runs", "list"],
    "runs show": ["runs", "show", "1"],
    "tool history": ["tool", "history"],
    "tool rollback": ["tool", "rollback", "--cell", "sim"],
}


@pytest.mark.parametrize("where", ["a folder that does not exist", "an empty folder"])
@pytest.mark.parametrize("command", list(READERS))
def test_a_reading_command_on_a_folder_without_a_store_makes_nothing(tmp_path, capsys, command, where):
    folder = tmp_path / "typo" / "state"
    if where == "an empty folder":
        folder.mkdir(parents=True)
    code, out, err = run_cli(capsys, *READERS[command], "--state-dir", str(folder))
    assert code == 2 and out == ""
    assert one_message(err) == (f"cellcal: error: no results store in {folder} (nothing recorded there yet, "
                                "or a typo in --state-dir?)")
    if where == "an empty folder":
        assert list(folder.iterdir()) == []
    else:
        assert not (tmp_path / "typo").exists()


def test_a_reading_command_with_json_prints_the_error_object(tmp_path, capsys):
    code, out, err = run_cli(capsys, "runs", "list", "--state-dir", str(tmp_path / "typo"), "--json")
    assert code == 2 and json.loads(out)["error"]["code"] == 2 and "no results store" in one_message(err)


# -- the daemon: a store it cannot write -----------------------------------------------------------


def _store_made_by_someone_else(folder: Path) -> bytes:
    store = Store.open(folder)
    store.event("start", "made before the service first started")
    store.close()
    return (folder / "cellcal.db").read_bytes()


@pytest.mark.skipif(os.geteuid() == 0, reason="root ignores file modes (the root-only case below covers it)")
@pytest.mark.parametrize("what", ["the store file", "the folder"])
def test_the_daemon_refuses_a_store_it_cannot_write_naming_the_file_and_the_fix(tmp_path, capsys, what):
    folder = tmp_path / "state"
    folder.mkdir()
    content = _store_made_by_someone_else(folder)
    locked = folder / "cellcal.db" if what == "the store file" else folder
    locked.chmod(0o444 if what == "the store file" else 0o555)
    try:
        code, out, err = run_cli(capsys, "daemon", "--cell", "sim", "--state-dir", str(folder))
    finally:
        locked.chmod(0o644 if what == "the store file" else 0o755)
    line = one_message(err)
    assert code == 2 and out == ""
    assert f"{locked} is not writable by user" in line and f"fix: chmod -R u+rwX {folder}" in line, line
    assert (folder / "cellcal.db").read_bytes() == content  # nothing written
    assert not (folder / "cellcal.lock").exists()  # refused before it took anything


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root to make a store as root and start as another user")
@pytest.mark.parametrize("what", ["the store file", "the folder"])
def test_a_store_root_made_is_named_with_its_owner_and_the_chown_that_fixes_it(what):
    """`cellcal runs list` as root made the store before the service (user nobody here) first started."""
    top = Path(tempfile.mkdtemp(prefix="cellcal-store-"))  # not under pytest's root-only 0700 folder
    try:
        top.chmod(0o755)
        folder = top / "state"
        folder.mkdir()
        content = _store_made_by_someone_else(folder)  # root's, mode 0644
        if what == "the store file":
            os.chown(folder, NOBODY, NOBODY)  # the service's folder; the file in it root's
        answer = as_nobody(lambda: Store.open(folder, create=True).close(), StoreError)
        locked = folder / "cellcal.db" if what == "the store file" else folder
        assert answer.startswith(f"{locked} is not writable by user nobody (uid {NOBODY})"), answer
        assert "it belongs to root" in answer and answer.endswith(f"fix: chown -R nobody: {folder}"), answer
        assert (folder / "cellcal.db").read_bytes() == content
    finally:
        shutil.rmtree(top)


def test_the_state_folder_check_makes_a_missing_folder_and_refuses_a_file(tmp_path):
    made = check_state_folder(tmp_path / "new" / "state", create=True)
    assert made.is_dir() and stat.S_ISDIR(made.stat().st_mode)
    (tmp_path / "afile").write_text("x")
    with pytest.raises(StoreError, match="exists and is not a folder"):
        check_state_folder(tmp_path / "afile", create=True)


# -- the claims ------------------------------------------------------------------------------------


def test_the_state_folder_lock_names_its_holder_and_is_free_once_released(tmp_path):
    first = FolderLock(tmp_path).acquire()
    try:
        assert (tmp_path / "cellcal.lock").read_text() == f"{os.getpid()}\n"
        with pytest.raises(InUseError) as refused:  # flock: two opens of the file conflict even in one process
            FolderLock(tmp_path).acquire()
        assert refused.value.holder.pid == os.getpid()
        assert f"holds the state folder {tmp_path}" in str(refused.value)
        assert str(refused.value).endswith("nothing was changed")
    finally:
        first.release()
    FolderLock(tmp_path).acquire().release()


def test_a_device_claim_names_its_holder_through_the_socket_and_is_free_once_released():
    device = Device("robot 127.0.0.1 (a test's)", f"test:{os.getpid()}:{id(object())}")
    first = DeviceClaim(device).acquire()
    try:
        with pytest.raises(InUseError) as refused:
            DeviceClaim(device).acquire()
        assert refused.value.holder.pid == os.getpid()  # read from the claim's socket (SO_PEERCRED)
        assert refused.value.holder.cmdline  # and its command line from /proc
        assert "holds robot 127.0.0.1 (a test's)" in str(refused.value)
    finally:
        first.release()
    DeviceClaim(device).acquire().release()


def test_the_devices_of_a_cell_are_its_networked_robot_and_panel_with_the_drivers_defaults():
    assert devices(load_cell("sim")) == []  # in process: nothing another process could reach
    net = load_cell("sim-net")
    assert devices(net) == [Device("robot 127.0.0.1", "robot:127.0.0.1"),
                            Device("panel 127.0.0.1:5020 unit 1", "panel:127.0.0.1:5020:1")]  # unit_id: default
    dual = load_cell("sim-dual-net")
    robots = [d.label for d in devices(dual, ("robot",))]
    assert len(robots) == 2 and len(set(robots)) == 2  # each of the two robots is claimed


# -- rollback: the robot it came from; walking back ------------------------------------------------

FRAMES = [np.array([0.0, 0.0, 0.150, 0.0, 0.0, 0.0]) + np.array([k * 1e-4, 0.0, k * 1e-4, 0.0, 0.0, 0.0])
          for k in range(4)]  # F0 (before run 1), F1, F2, F3 (written by runs 1, 2, 3)


def store_with_writes(folder: Path, cell_path: str, runs: int = 3) -> Store:
    store = Store.open(folder)
    for k in range(1, runs + 1):
        run = store.begin_run("tcp-npoint", cell_path)
        store.finish_run(run, "done", 0, "written back")
        store.record_tool_frame(run, "write", FRAMES[k - 1], FRAMES[k])
    return store


def rollbacks(folder: Path) -> list[tuple[int, list]]:
    store = Store.open(folder)
    try:
        return [(f["run_id"], f["frame_after"]) for f in store.tool_frames() if f["action"] == "rollback"]
    finally:
        store.close()


def test_a_rollback_with_a_cell_other_than_the_runs_is_refused_naming_both(tmp_path, capsys):
    net_path = str(shipped_cells()["sim-net"])
    store_with_writes(tmp_path, net_path).close()
    code, out, err = run_cli(capsys, "tool", "rollback", "3", "--cell", "sim", "--state-dir", str(tmp_path))
    line = one_message(err)
    assert code == 2 and out == ""
    assert f"run 3 wrote to the robot of cell sim-net ({net_path}: robot 127.0.0.1)" in line, line
    assert "not to --cell sim (cell sim: a simulated robot, in process)" in line and f"give --cell {net_path}" in line
    assert rollbacks(tmp_path) == []  # nothing recorded, nothing connected


def test_repeated_rollbacks_walk_back_through_the_history_and_a_run_restores_its_own(tmp_path, capsys):
    sim_path = str(load_cell("sim").path)
    store_with_writes(tmp_path, sim_path).close()
    rollback = ["tool", "rollback", "--cell", "sim", "--state-dir", str(tmp_path)]
    code, _, err = run_cli(capsys, *rollback)  # undoes run 3: the frame from before it, F2
    assert code == 0 and "next rollback without RUN undoes run 2's write-back" in err
    code, _, err = run_cli(capsys, *rollback)  # then run 2: F1, not F2 again
    assert code == 0 and "next rollback without RUN undoes run 1's write-back" in err
    code, _, _ = run_cli(capsys, "tool", "rollback", "3", "--cell", "sim", "--state-dir", str(tmp_path))
    assert code == 0  # a named run: the frame from before its write, whatever came since
    code, _, err = run_cli(capsys, *rollback)  # run 1 is still in effect underneath: F0
    assert code == 0 and "nothing left to undo" in err
    assert rollbacks(tmp_path) == [(3, FRAMES[2].tolist()), (2, FRAMES[1].tolist()), (3, FRAMES[2].tolist()),
                                   (1, FRAMES[0].tolist())]
    code, out, err = run_cli(capsys, *rollback)
    assert code == 2 and out == ""
    assert "no write-back to undo" in one_message(err) and "every one recorded has been rolled back already" in err
    assert len(rollbacks(tmp_path)) == 4


def test_a_rollback_of_a_run_that_wrote_nothing_is_refused(tmp_path, capsys):
    store_with_writes(tmp_path, str(load_cell("sim").path), runs=1).close()
    code, out, err = run_cli(capsys, "tool", "rollback", "7", "--cell", "sim", "--state-dir", str(tmp_path))
    assert code == 2 and "no write-back of run 7" in one_message(err)
