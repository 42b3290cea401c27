"""``cellcal demo``: the whole product on the simulated cell, as ``make demo`` runs it.

Starts the network fakes (``cellcal sim-cell``), starts the service on them (``cellcal
daemon``, waiting for its systemd READY), plays the operator: selects the routine and
presses start through Modbus, as a panel would; waits for the run to end, prints the
tool frame written back to the (fake) controller beside the simulation's hidden truth and
the report's path, and stops everything cleanly.
"""
from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from pymodbus.client import ModbusTcpClient

from cellcal.config.robot_files import load_robot
from cellcal.drivers import registry as drivers_registry
from cellcal.drivers.modbus.panel import PanelMap
from cellcal.routines.framework import registry
from cellcal.routines.framework.base import FRAME_KEYS, gate_line, tool_frame_json
from cellcal.daemon.cells import load_cell
from cellcal.cli.common import UsageError, print_progress
from cellcal.daemon.panel import panel_routines
from cellcal.daemon.result_codes import RESULT_MEANINGS, ResultCode

RUN_TIMEOUT_S = 180.0
READY_TIMEOUT_S = 60.0


def _cellcal(*args: str) -> list[str]:
    return [sys.executable, "-m", "cellcal.cli.main", *args]


def _echo(stream, prefix: str) -> threading.Thread:
    def pump():
        for line in stream:
            print(f"{prefix}{line.rstrip()}", file=sys.stderr, flush=True)
    thread = threading.Thread(target=pump, daemon=True)
    thread.start()
    return thread


def _stop(proc: subprocess.Popen | None) -> None:
    if proc is None or proc.poll() is not None:
        return
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def start_daemon(cell_path, state_dir, notify_path, *, stderr, on_start=lambda proc: None,
                 extra=()) -> subprocess.Popen:
    """``cellcal daemon`` on a cell, returned once it has sent READY=1 to its notify socket
    (systemd's protocol, on a socket made at `notify_path`); `on_start(proc)` runs before the
    wait, e.g. to echo its log. RuntimeError, the daemon stopped, if READY does not come."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as notify:
        notify.bind(str(notify_path))
        notify.settimeout(READY_TIMEOUT_S)
        env = dict(os.environ, NOTIFY_SOCKET=str(notify_path))
        daemon = subprocess.Popen(_cellcal("daemon", "--cell", str(cell_path), "--state-dir", str(state_dir), *extra),
                                  env=env, stdout=subprocess.DEVNULL, stderr=stderr, text=True)
        on_start(daemon)
        try:
            while b"READY=1" not in notify.recv(4096):
                pass
        except socket.timeout:
            _stop(daemon)
            raise RuntimeError(f"the daemon did not get ready within {READY_TIMEOUT_S:g} s") from None
        finally:
            Path(notify_path).unlink()
    return daemon


def cmd_demo(args) -> int:
    cell = load_cell(args.cell)
    selectors = panel_routines()
    number = next((k for k, v in selectors.items() if v == args.routine), None)
    if number is None:
        raise UsageError(f"--routine {args.routine}: not on the panel's selector ({', '.join(selectors.values())})")
    why_not = registry.unavailable(args.routine, cell)
    if why_not is not None:
        offered = [name for name in selectors.values() if registry.unavailable(name, cell) is None]
        raise UsageError(f"--routine {args.routine}: this cell cannot run it ({why_not}); it can run: "
                         f"{', '.join(offered) or 'none'}")
    panel = cell.drivers.get("panel")
    if panel is None or panel.name != "modbus":
        raise UsageError(f"{cell.path}: the demo presses start through a Modbus panel; this cell has none")
    host, port = panel.options.get("host", "127.0.0.1"), panel.options.get("port", 502)
    unit, addresses = panel.options.get("unit_id", 1), PanelMap.of_options(panel.options)
    work = Path(tempfile.mkdtemp(prefix="cellcal-demo-"))
    fakes = daemon = None
    notify_path = work / "notify.sock"
    try:
        print_progress(f"starting the simulated cell's fakes ({cell.path})")
        fakes = subprocess.Popen(_cellcal("sim-cell", "--cell", cell.path), stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True)
        line = fakes.stdout.readline()
        if "listening" not in line:
            raise RuntimeError(f"the fakes did not start: {line}{fakes.stderr.read()}")
        print_progress(line.strip().removeprefix("cellcal "))
        _echo(fakes.stderr, "  fakes: ")
        daemon = start_daemon(cell.path, work / "state", notify_path, stderr=subprocess.PIPE,
                              on_start=lambda proc: _echo(proc.stderr, "  daemon: "))
        print_progress(f"the daemon is ready; the operator selects {args.routine} ({number}) and presses start")
        operator = ModbusTcpClient(host, port=port, timeout=2.0)
        if not operator.connect():
            raise RuntimeError(f"cannot reach the panel at {host}:{port}")

        def register(address: int) -> int:
            return operator.read_holding_registers(address, count=1, device_id=unit).registers[0]

        try:
            counter = register(addresses.run_counter_register)
            operator.write_register(addresses.routine_selector_register, number, device_id=unit)
            operator.write_coil(addresses.start_request_coil, True, device_id=unit)
            deadline = time.monotonic() + RUN_TIMEOUT_S
            while register(addresses.run_counter_register) == counter:
                if time.monotonic() > deadline or daemon.poll() is not None:
                    raise RuntimeError("the run did not end in time" if daemon.poll() is None
                                       else "the daemon ended during the run")
                time.sleep(0.2)
            code = ResultCode(register(addresses.result_code_register))
        finally:
            operator.close()
        shown = subprocess.run(_cellcal("runs", "list", "--json", "--limit", "1", "--state-dir",
                                        str(work / "state")), capture_output=True, text=True, check=True)
        run_id = json.loads(shown.stdout)["runs"][0]["id"]
        detail = json.loads(subprocess.run(_cellcal("runs", "show", str(run_id), "--json", "--state-dir",
                                                    str(work / "state")), capture_output=True, text=True,
                                           check=True).stdout)
        print(f"\nrun {run_id}: {args.routine} -> {detail['state']}, result code {int(code)} "
              f"({RESULT_MEANINGS[code]})")
        result = detail.get("result") or {}
        frame = (result.get("tool_frame") or {}).get("pose_m_rad")
        truth = drivers_registry.simulated_truth(cell, load_robot(cell.robot))
        if frame is not None:
            f = tool_frame_json(frame)
            t = tool_frame_json(truth.tool.tcp_pose)
            print("                       x mm       y mm       z mm     rx deg     ry deg     rz deg")
            for label, v in (("written back", f), ("hidden truth", t)):
                print(f"  {label:<14}" + "".join(f"{v[k]:11.4f}" for k in FRAME_KEYS))
            score = truth.score_tool_frame(frame)
            print(f"  error against the truth: TCP {score['position_error_mm']:.4f} mm, "
                  f"axis {score['axis_error_deg']:.4f} deg")
        for g in result.get("gates", []):
            print(f"  {gate_line(g)}")
        print(f"  report: {detail.get('report')}\n  dataset: {detail.get('dataset')}\n  store: {work / 'state'}")
        return 0 if code is ResultCode.OK else 1
    finally:
        _stop(daemon)
        _stop(fakes)
        print_progress("stopped the daemon and the fakes")


def add_parser(sub) -> None:
    p = sub.add_parser("demo", help="the whole product on the simulated network cell (make demo)",
                       description="Start the simulated cell's network fakes and the daemon on them, press start "
                                   "through the Modbus panel, and print the written-back tool frame beside the "
                                   "hidden truth and the run's report.")
    p.add_argument("--cell", default="sim-net", metavar="CELL.yaml", help="a networked simulated cell (default sim-net)")
    p.add_argument("--routine", default="tcp-laser", help="the routine the operator selects (default tcp-laser)")
    p.set_defaults(func=cmd_demo)
