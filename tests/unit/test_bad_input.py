"""Bad input, one table: each row is one way a person or a careless script gets it wrong.

Every probe runs the real command line and asserts the exit status (2: the input is at
fault, 1: the computation showed the data cannot be used), one message naming what is
wrong, no traceback, and nothing hanging. Adding the next bad input is one row.
"""
from __future__ import annotations

import json
import math
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cellcal.cli.main import main
from support.cli_run import refused  # tests/support/cli_run.py

ROW = 5  # the data row that gets spoiled (1-based, after the header)


@pytest.fixture(scope="module")
def ok(tmp_path_factory) -> Path:
    """A good 40-pose campaign: cal.csv and val.csv."""
    folder = tmp_path_factory.mktemp("ok")
    assert main(["sim-campaign", "--robot", "ur10e", "--poses", "40", "--validate-poses", "40",
                 "--out", str(folder)]) == 0
    return folder


def rewrite(ok: Path, tmp: Path, name: str, change) -> Path:
    """cal.csv with every data row passed through change(columns, fields, row) (row 1-based)."""
    lines = (ok / "cal.csv").read_text().splitlines()
    header_at = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    columns = {c: k for k, c in enumerate(lines[header_at].split(","))}
    for i in range(header_at + 1, len(lines)):
        fields = lines[i].split(",")
        change(columns, fields, i - header_at)
        lines[i] = ",".join(fields)
    path = tmp / name
    path.write_text("\n".join(lines) + "\n")
    return path


def spoil(ok: Path, tmp: Path, column: str, value: str, rows=(ROW,), name: str = "bad.csv") -> Path:
    """cal.csv with `column` set to `value` in the given data rows (every row with rows=None)."""
    def change(columns, fields, row):
        if rows is None or row in rows:
            fields[columns[column]] = value
    return rewrite(ok, tmp, name, change)


def degrees_under_rad(ok: Path, tmp: Path) -> Path:
    def change(columns, fields, row):
        for k in range(1, 7):
            c = columns[f"q{k}_rad"]
            fields[c] = repr(math.degrees(float(fields[c])))
    return rewrite(ok, tmp, "deg.csv", change)


def all_zero(ok: Path, tmp: Path) -> Path:
    def change(columns, fields, row):
        for c in ("x_mm", "y_mm", "z_mm"):
            fields[columns[c]] = "0"
    return rewrite(ok, tmp, "zero.csv", change)


def swapped_joints(ok: Path, tmp: Path) -> Path:
    def change(columns, fields, row):
        a, b = columns["q2_rad"], columns["q4_rad"]
        fields[a], fields[b] = fields[b], fields[a]
    return rewrite(ok, tmp, "swapped.csv", change)


def narrow_robot(tmp: Path) -> Path:
    """The UR10e with every joint limited to +-10 degrees."""
    from cellcal.config.robot_files import shipped_robots

    text = shipped_robots()["ur10e"].read_text()
    text = "\n".join(line for line in text.splitlines() if not line.startswith("joint_limits"))
    path = tmp / "narrow.yaml"
    path.write_text(text + "\njoint_limits: " + json.dumps([[-10, 10]] * 6) + "\n")
    return path


def own_targets(ok: Path, tmp: Path) -> Path:
    lines = (ok / "cal.csv").read_text().splitlines()
    header_at = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    lines[header_at] += ",target"
    for i in range(header_at + 1, len(lines)):
        lines[i] += f",t{i}"
    path = tmp / "targets.csv"
    path.write_text("\n".join(lines) + "\n")
    return path


def cr_only(ok: Path, tmp: Path) -> Path:
    path = tmp / "cr.csv"
    path.write_bytes((ok / "cal.csv").read_bytes().replace(b"\n", b"\r"))
    return path


def cell_with_tracker_port(tmp: Path, port) -> Path:
    from support.cell_edits import edited_cell  # tests/support/cell_edits.py

    return edited_cell(tmp, "sim-net", {"drivers": {"tracker": {"port": port}}})


def with_payload(ok: Path, tmp: Path, value: str) -> Path:
    """cal.csv with a payload_kg column, 5 kg in every row but row ROW."""
    lines = (ok / "cal.csv").read_text().splitlines()
    header_at = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    lines[header_at] += ",payload_kg"
    for i in range(header_at + 1, len(lines)):
        lines[i] += "," + (value if i - header_at == ROW else "5")
    path = tmp / "payload.csv"
    path.write_text("\n".join(lines) + "\n")
    return path


def a_file(tmp: Path) -> Path:
    path = tmp / "a-file"
    path.write_text("not a folder")
    return path


def alias_bomb(tmp: Path) -> Path:
    """The sim cell with tool.tcp_m a billion laughs: nested aliases standing for 10**10 numbers."""
    from cellcal.config.cell_files import shipped_cells

    bomb = ["lol0: &lol0 [1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0]"]
    bomb += [f"lol{i}: &lol{i} [{', '.join([f'*lol{i - 1}'] * 10)}]" for i in range(1, 10)]
    path = tmp / "bomb.yaml"
    path.write_text("\n".join(bomb) + "\n" + shipped_cells()["sim"].read_text().replace("tcp_m: [0.0, 0.0, 0.150]",
                                                                                        "tcp_m: *lol9"))
    return path


def targets(tmp: Path, row: str) -> Path:
    path = tmp / "t.csv"
    path.write_text(f"x_mm,y_mm,z_mm\n{row}\n")
    return path


def far_stylus(tmp: Path) -> Path:
    from support.cell_edits import edited_cell

    return edited_cell(tmp, "sim", {"stylus": {"centre_m": [-1.15, -0.4, 0.4]}})


def without_tracker(tmp: Path) -> Path:
    from support.cell_edits import DELETE, edited_cell

    return edited_cell(tmp, "sim", {"drivers": {"tracker": DELETE}})


# (id, argv builder (ok, tmp) -> list, exit status, fragments of the message on stderr)
CASES = [
    ("huge value hangs identify", lambda ok, t: ["identify", "--robot", "ur10e", "--data",
                                                  spoil(ok, t, "x_mm", "1e308")], 2, ["x_mm", "over 100 m"]),
    ("huge value hangs analyze", lambda ok, t: ["analyze", "--robot", "ur10e", "--data",
                                                 spoil(ok, t, "y_mm", "1e160")], 2, ["y_mm", "over 100 m"]),
    ("a billion mm", lambda ok, t: ["identify", "--robot", "ur10e", "--data", spoil(ok, t, "x_mm", "1e9")], 2,
     [f":{ROW + 2}: column 'x_mm'"]),
    ("degrees under _rad headers", lambda ok, t: ["identify", "--robot", "ur10e", "--data",
                                                   degrees_under_rad(ok, t)], 2,
     ["q1_rad", "beyond two turns", "degrees under a _rad header?"]),
    ("outside a narrow model's limits", lambda ok, t: ["identify", "--robot", narrow_robot(t), "--data",
                                                        ok / "cal.csv"], 2, ["outside", "joint 1 limits", "lines"]),
    ("no spread in the positions", lambda ok, t: ["identify", "--robot", "ur10e", "--data",
                                                   all_zero(ok, t)], 1, ["degenerate"]),
    ("every row its own target", lambda ok, t: ["identify", "--robot", "ur10e", "--data", own_targets(ok, t)], 1,
     ["measure each target at several poses"]),
    ("thermal drift without time or temperature", lambda ok, t: ["analyze", "--robot", "ur10e", "--data",
                                                                  ok / "cal.csv", "--causes", "thermal_drift"], 2,
     ["thermal_drift", "temp_c or t_s"]),
    ("latency without joint velocities", lambda ok, t: ["analyze", "--robot", "ur10e", "--data", ok / "cal.csv",
                                                        "--causes", "trigger_latency"], 2, ["dq1_rad_s"]),
    ("effect on joint 0", lambda ok, t: ["sim-data", "--effect", "joint_compliance:0", "-o", t / "s.csv"], 2,
     ["from 1 to 6"]),
    ("effect on joint 7 of 6", lambda ok, t: ["sim-data", "--effect", "joint_compliance:7", "-o", t / "s.csv"], 2,
     ["from 1 to 6"]),
    ("prior of zero", lambda ok, t: ["identify", "--robot", "ur10e", "--data", ok / "cal.csv", "--prior-mm", "0"],
     2, ["argument --prior-mm: must be a number above 0"]),
    ("negative prior", lambda ok, t: ["identify", "--robot", "ur10e", "--data", ok / "cal.csv",
                                      "--prior-mm", "-1"], 2, ["--prior-mm"]),
    ("prior nan", lambda ok, t: ["identify", "--robot", "ur10e", "--data", ok / "cal.csv", "--prior-mm", "nan"],
     2, ["--prior-mm"]),
    ("prior inf", lambda ok, t: ["identify", "--robot", "ur10e", "--data", ok / "cal.csv", "--prior-mm", "inf"],
     2, ["--prior-mm"]),
    ("sim-data into a missing folder", lambda ok, t: ["sim-data", "-o", t / "no" / "such" / "s.csv"], 2,
     ["does not exist"]),
    ("sim-data onto a folder", lambda ok, t: ["sim-data", "-o", t], 2, ["is a folder"]),
    ("sim-campaign into /proc", lambda ok, t: ["sim-campaign", "--out", "/proc/cellcal-x"], 2,
     ["cannot make the folder"]),
    ("sim-data with no poses", lambda ok, t: ["sim-data", "--poses", "0", "-o", t / "s.csv"], 2, ["--poses"]),
    ("negative seed", lambda ok, t: ["sim-campaign", "--seed", "-1", "--out", t / "c"], 2, ["--seed"]),
    ("rms nan", lambda ok, t: ["sim-data", "--rms-mm", "nan", "-o", t / "s.csv"], 2, ["--rms-mm"]),
    ("negative rms", lambda ok, t: ["sim-data", "--rms-mm", "-1", "-o", t / "s.csv"], 2, ["--rms-mm"]),
    ("a device as the data file", lambda ok, t: ["identify", "--robot", "ur10e", "--data", "/dev/zero"], 2,
     ["not a regular file"]),
    ("CR-only line endings", lambda ok, t: ["identify", "--robot", "ur10e", "--data", cr_only(ok, t)], 2,
     ["CR alone"]),
    ("an empty robot name", lambda ok, t: ["identify", "--robot", "", "--data", ok / "cal.csv"], 2,
     ["no robot given"]),
    ("tracker port as text", lambda ok, t: ["sim-cell", "--cell", cell_with_tracker_port(t, "5030")], 2,
     ["[drivers.tracker.port]", "not an integer"]),
    ("tracker port too high", lambda ok, t: ["sim-cell", "--cell", cell_with_tracker_port(t, 70000)], 2,
     ["[drivers.tracker.port]", "out of range"]),
    ("tracker port zero", lambda ok, t: ["sim-cell", "--cell", cell_with_tracker_port(t, 0)], 2,
     ["[drivers.tracker.port]"]),
    # issue 18, section 4: numbers bounded where they are parsed ...
    ("daemon polling every -1 s", lambda ok, t: ["daemon", "--cell", "sim", "--poll-s", "-1"], 2,
     ["argument --poll-s", "0.005 to 10 s"]),
    ("daemon polling every 0 s", lambda ok, t: ["daemon", "--cell", "sim", "--poll-s", "0"], 2, ["--poll-s"]),
    ("daemon polling every nan s", lambda ok, t: ["daemon", "--cell", "sim", "--poll-s", "nan"], 2, ["--poll-s"]),
    ("daemon polling every 1e9 s", lambda ok, t: ["daemon", "--cell", "sim", "--poll-s", "1e9"], 2, ["--poll-s"]),
    ("sim-data with 1e8 poses", lambda ok, t: ["sim-data", "--poses", "100000000", "-o", t / "s.csv"], 2,
     ["argument --poses", "1 to 100000"]),
    ("a run id beyond the store's integers", lambda ok, t: ["runs", "show", "1" + "0" * 30], 2, ["argument ID"]),
    # ... output paths checked before anything is computed or moved ...
    ("sim-data into /proc", lambda ok, t: ["sim-data", "-o", "/proc/x.csv"], 2,
     ["-o /proc/x.csv", "cannot create the file"]),
    ("run's datasets into a file", lambda ok, t: ["run", "tcp-npoint", "--out", a_file(t)], 2,
     ["--out", "exists and is not a folder"]),
    ("run's datasets into /proc", lambda ok, t: ["run", "tcp-npoint", "--out", "/proc/x"], 2,
     ["--out /proc/x", "cannot make the folder"]),
    ("compensate into /proc", lambda ok, t: ["compensate", "--robot", "ur5e", "--targets", "t.csv", "-o",
                                             "/proc/x.csv"], 2, ["-o /proc/x.csv"]),
    ("import into /proc", lambda ok, t: ["import", "dlr-justin", "x.txt", "-o", "/proc/x.csv"], 2,
     ["-o /proc/x.csv"]),
    ("identify's model into /proc", lambda ok, t: ["identify", "--robot", "ur10e", "--data", ok / "cal.csv",
                                                   "--write-model", "/proc/x.yaml"], 2, ["--write-model /proc/x.yaml"]),
    ("analyze's report onto a file", lambda ok, t: ["analyze", "--robot", "ur10e", "--data", ok / "cal.csv",
                                                    "--report", a_file(t)], 2, ["--report", "not a folder"]),
    ("iso9283's report into /proc", lambda ok, t: ["iso9283", "--robot", "ur10e", "--data", ok / "cal.csv",
                                                   "--report", "/proc/x"], 2, ["--report /proc/x"]),
    # ... files that cannot be what they claim ...
    ("an alias bomb in a cell file", lambda ok, t: ["run", "tcp-laser", "--cell", alias_bomb(t), "--dry-run"], 2,
     ["aliases (*name) expand to", "memory bomb"]),
    ("compensate's target 1e308 mm away", lambda ok, t: ["compensate", "--robot", "ur5e", "--targets",
                                                         targets(t, "1e308,0,0"), "-o", t / "o.csv", "--seed-deg",
                                                         "0", "-90", "90", "-90", "-90", "0", "--tcp-mm", "0", "0",
                                                         "100"], 2, ["t.csv:2: column 'x_mm'", "over 100 m"]),
    ("a payload of 1e9 kg", lambda ok, t: ["identify", "--robot", "ur10e", "--data", with_payload(ok, t, "1e9")], 2,
     [f":{ROW + 2}: column 'payload_kg'", "more than any arm carries"]),
    # ... and a plan the cell cannot carry out is input at fault, for every routine alike
    ("tcp-stylus with the stylus out of reach", lambda ok, t: ["run", "tcp-stylus", "--cell", far_stylus(t),
                                                               "--dry-run"], 2, ["plan refused", "reduce tilt_deg"]),
    ("tcf with the stylus out of reach", lambda ok, t: ["run", "tcf", "--cell", far_stylus(t), "--dry-run"], 2,
     ["plan refused", "cannot be reached"]),
    ("tracker on a cell without a tracker", lambda ok, t: ["run", "tracker", "--cell", without_tracker(t),
                                                           "--dry-run"], 2, ["needs a tracker in [drivers]"]),
]


@pytest.mark.parametrize("name, argv, code, needles", CASES, ids=[c[0] for c in CASES])
def test_bad_input_gets_one_message(ok, tmp_path, capsys, name, argv, code, needles):
    refused(capsys, argv(ok, tmp_path), code, needles)


@pytest.mark.parametrize("name, argv, code, needles", CASES[:1], ids=["identify"])
def test_bad_input_with_json_prints_one_error_object(ok, tmp_path, capsys, name, argv, code, needles):
    assert main([str(a) for a in argv(ok, tmp_path)] + ["--json"]) == code
    out, err = capsys.readouterr()
    error = json.loads(out)["error"]
    assert error["code"] == code and needles[0] in error["message"]


def test_the_huge_value_no_longer_hangs_as_a_process(ok, tmp_path):
    proc = subprocess.run([sys.executable, "-m", "cellcal.cli.main", "identify", "--robot", "ur10e", "--data",
                           str(spoil(ok, tmp_path, "x_mm", "1e308"))], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "over 100 m" in proc.stderr


def test_a_cause_that_cannot_be_scored_is_named_when_others_can(ok, capsys):
    assert main(["analyze", "--robot", "ur10e", "--data", str(ok / "cal.csv"), "--causes", "thermal_drift",
                 "backlash", "--json"]) == 0
    out, err = capsys.readouterr()
    finding = json.loads(out)
    assert finding["not_scored"] == {"thermal_drift": "needs a temp_c or t_s column (temperature or time of "
                                                      "each measurement)"}
    assert any("thermal_drift not scored" in n for n in finding["notes"]) and "thermal_drift not scored" in err


def test_a_report_that_cannot_be_written_keeps_the_finding(ok, tmp_path, capsys, monkeypatch):
    """A folder that cannot take a report is refused before the analysis (a row above); one that fails
    while the report is written (a full disk) still leaves the finding printed."""
    import cellcal.reports.analysis

    def full_disk(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(cellcal.reports.analysis, "write_report", full_disk)
    assert main(["analyze", "--robot", "ur10e", "--data", str(ok / "cal.csv"), "--report",
                 str(tmp_path / "report")]) == 2
    out, err = capsys.readouterr()
    assert "finding:" in out  # the result came first
    assert "cannot write the report" in err and "Traceback" not in err


def test_a_report_leaves_no_stale_plot_of_an_earlier_run(ok, tmp_path, capsys):
    report = tmp_path / "report"
    report.mkdir()
    (report / "residual_vs_regressor.png").write_text("an earlier run's plot")
    (report / "notes.txt").write_text("the user's own file")
    assert main(["analyze", "--robot", "ur10e", "--data", str(ok / "cal.csv"), "--causes", "backlash",
                 "--report", str(report)]) == 0
    out = capsys.readouterr().out
    assert "finding: none" in out  # clean data: no effect plot is drawn ...
    assert not (report / "residual_vs_regressor.png").exists()  # ... and the earlier one is gone
    assert (report / "notes.txt").exists() and (report / "report.html").exists()


def test_a_fit_far_worse_than_any_arm_says_the_data_are_wrong(ok, tmp_path, capsys):
    """Joints 2 and 4 swapped: every value is in range, no geometry can explain it."""
    assert main(["identify", "--robot", "ur10e", "--data", str(swapped_joints(ok, tmp_path))]) == 1
    err = capsys.readouterr().err
    assert "something is wrong with the data" in err and "Traceback" not in err


# -- the fakes refuse what the real devices would -----------------------------------------

def test_the_fake_tracker_refuses_a_request_line_over_the_protocols_512_bytes():
    from cellcal.sims.net.tracker_server import TrackerServer

    server = TrackerServer(lambda target: np.zeros(3)).start()
    try:
        with socket.create_connection((server.host, server.port), timeout=2.0) as conn:
            conn.sendall(b"MEAS " + b"x" * 3000 + b" 1\n")
            reply = conn.makefile("rb").readline()
        assert reply.startswith(b"ERR") and b"line too long" in reply
    finally:
        server.stop()


def test_a_fake_ur_session_drops_a_client_that_sends_an_endless_line():
    from cellcal.sims.fake_ur.sessions import MAX_LINE_CHARS, _lines

    ours, theirs = socket.socketpair()
    with ours, theirs:
        theirs.sendall(b'{"cmd": "state"}\n' + b"y" * (MAX_LINE_CHARS * 4))
        theirs.shutdown(socket.SHUT_WR)
        lines = list(_lines(ours))
        assert lines == ['{"cmd": "state"}\n']  # the flood ends the connection, it is not buffered
        assert theirs.recv(100).startswith(b"error: line too long")


def test_the_fake_ur_refuses_joint_values_no_robot_has():
    from cellcal.sims.fake_ur.controller import FakeUrController

    controller = FakeUrController("127.0.0.1")
    for q in ([float("nan")] * 6, [0.0] * 5, [0.0, 0.0, 0.0, 0.0, 0.0, 99.0]):
        reply = controller.control({"cmd": "set_q", "q": q})
        assert not reply["ok"] and "q " in reply["error"], reply
    assert np.all(np.isfinite(controller.arm.q))
