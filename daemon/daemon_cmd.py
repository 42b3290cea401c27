"""``cellcal daemon``, ``cellcal runs`` and ``cellcal tool``: the service and its records.

``cellcal daemon --cell CELL.yaml`` connects the cell's devices, checks them, tells
systemd it is ready, then serves the operator panel until SIGTERM or SIGINT: a start
request runs the selected routine (:mod:`.service`). After any crash it comes up idle:
a run found open in the store is recorded as interrupted, and nothing moves by itself.
"""
from __future__ import annotations

import json
import logging
import signal
import sys
import threading
import time

import numpy as np

from ..drivers.interfaces import DeviceError, RobotState
from ..routines.base import tool_frame_json
from .cells import load_cell, open_drivers
from .cli_common import UsageError
from .notify import Notifier
from .run_report import write_run_report
from .service import RESULT_MEANINGS, ResultCode, Service
from .store import Store, StoreError, state_dir
from .write_back import ControllerFrames, replace_frames, stored_from_json

log = logging.getLogger("cellcal.daemon")
STOP_WAIT_S = 1.5  # how long a stop waits for the running routine to halt before leaving


def _store(args) -> Store:
    try:
        return Store.open(state_dir(args.state_dir))
    except StoreError as exc:
        raise UsageError(str(exc)) from None


def cmd_daemon(args) -> int:
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="cellcal: %(message)s", force=True)
    cell = load_cell(args.cell)
    store = _store(args)
    folder = state_dir(args.state_dir)
    notifier = Notifier()
    stopping = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stopping.set()) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        interrupted = store.mark_interrupted(int(ResultCode.INTERRUPTED))
        for run_id in interrupted:
            log.warning("run %d: interrupted (the daemon stopped during it); nothing was written back", run_id)
        store.event("start", cell.path)
        try:
            drivers = open_drivers(cell)
        except DeviceError as exc:
            log.error("cannot connect the cell's devices: %s", exc)
            store.event("fault", str(exc))
            return 1
        with drivers:
            try:
                state = drivers.robot.state()
            except DeviceError as exc:
                log.error("the robot does not answer: %s", exc)
                return 1
            service = Service(cell, drivers, store, out_dir=folder / "datasets", notifier=notifier,
                              report=lambda run_id, result, st: write_run_report(folder / "reports", run_id, result),
                              reconnect=lambda: open_drivers(cell))
            service._panel("set_lamps", busy=False)
            service.discard_requests("pending when the service started")
            if interrupted:
                service.give_back_frame_of(interrupted[-1])
            log.info("ready: cell %s, robot %s", cell.name, state.value)
            notifier.ready(f"idle; robot {state.value}")
            try:
                while not stopping.is_set():
                    service.poll_panel()
                    notifier.watchdog()
                    stopping.wait(args.poll_s)
                notifier.stopping()
                log.info("stopping")
                if service.busy():
                    service.request_abort("the service is stopping")
                service.wait(STOP_WAIT_S)  # the run's end, and its last words to the panel and the store
                store.event("stop", None)
            finally:
                if service.drivers is not drivers:  # reconnected after a lost robot
                    service.drivers.close()
        return 0
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        notifier.close()
        store.close()


def cmd_runs_list(args) -> int:
    store = _store(args)
    try:
        runs = store.runs(args.limit)
        if args.json:
            print(json.dumps([_run_summary(r) for r in runs]))
            return 0
        if not runs:
            print("no runs recorded")
        for r in runs:
            when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(r.started_at))
            code = "" if r.result_code is None else f" code {r.result_code}"
            print(f"{r.id:5d}  {when}  {r.routine:<11} {r.state:<12}{code}  {r.reason or ''}")
        return 0
    finally:
        store.close()


def _run_summary(r) -> dict:
    return {"id": r.id, "routine": r.routine, "cell": r.cell, "started_at": r.started_at,
            "finished_at": r.finished_at, "state": r.state, "result_code": r.result_code, "reason": r.reason,
            "write_back": r.write_back}


def cmd_runs_show(args) -> int:
    store = _store(args)
    try:
        r = store.run(args.id)
        if r is None:
            raise UsageError(f"no run {args.id} in {store.path}")
        out = _run_summary(r)
        out.update(dataset=r.dataset_path, dataset_sha256=r.dataset_sha256, report=r.report_path,
                   states=[{"at": at, "state": s, "message": m} for at, s, m in store.states(r.id)],
                   parameters=store.parameters(r.id), gates=store.gates(r.id),
                   result=None if r.result_json is None else json.loads(r.result_json))
        if r.result_code is not None:
            out["result_meaning"] = RESULT_MEANINGS.get(ResultCode(r.result_code), "")
        if args.json:
            print(json.dumps(out))
            return 0
        print(f"run {r.id}: {r.routine} on {r.cell}: {r.state}"
              + ("" if r.result_code is None else f" (code {r.result_code}: {out['result_meaning']})"))
        if r.reason:
            print(f"  {r.reason}")
        for s in out["states"]:
            print(f"  {time.strftime('%H:%M:%S', time.localtime(s['at']))}  {s['state']}"
                  + (f": {s['message']}" if s["message"] else ""))
        for g in out["gates"]:
            print(f"  [{'pass' if g['passed'] else 'FAIL'}] {g['name']}: {g['why']}")
        for key in ("dataset", "report"):
            if out[key]:
                print(f"  {key}: {out[key]}")
        return 0
    finally:
        store.close()


def cmd_tool_history(args) -> int:
    store = _store(args)
    try:
        frames = store.tool_frames()
        if args.json:
            print(json.dumps(frames))
            return 0
        if not frames:
            print("no tool frame written yet")
        for f in frames:
            when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(f["at"]))
            after = tool_frame_json(f["frame_after"])
            print(f"{f['id']:4d}  {when}  {f['action']:<8} run {f['run_id']}  x {after['x_mm']:.4f} "
                  f"y {after['y_mm']:.4f} z {after['z_mm']:.4f} mm  rx {after['rx_deg']:.4f} "
                  f"ry {after['ry_deg']:.4f} rz {after['rz_deg']:.4f} deg"
                  + ("" if f["stored_after"] is None else
                     f"  (program start: generation {f['stored_after']['generation']})"))
        return 0
    finally:
        store.close()


def cmd_tool_rollback(args) -> int:
    """Restore the tool frames the controller had before a run's write-back (default: the latest):
    the running program's and the one the robot program applies at its start."""
    store = _store(args)
    try:
        writes = [f for f in store.tool_frames() if f["action"] == "write" and f["frame_before"] is not None]
        if args.run is not None:
            writes = [f for f in writes if f["run_id"] == args.run]
        if not writes:
            raise UsageError("no write-back to roll back" + (f" for run {args.run}" if args.run else ""))
        entry = writes[-1]
        frame = np.asarray(entry["frame_before"], dtype=float)
        target = ControllerFrames(frame, stored_from_json(entry["stored_before"]))
        cell = load_cell(args.cell)
        with open_drivers(cell) as drivers:
            if drivers.robot.state() is not RobotState.READY:
                raise UsageError(f"the robot is not ready ({drivers.robot.state().value}); nothing changed")
            current, failure = replace_frames(drivers.robot, target)
        if failure is not None:
            raise DeviceError("robot", f"rollback: {failure}")
        store.record_tool_frame(entry["run_id"], "rollback", current.running, frame, current.stored_json(),
                                target.stored_json() if current.stored is not None else None)
        f = tool_frame_json(frame)
        print(f"restored the tool frame from before run {entry['run_id']}: x {f['x_mm']:.4f} y {f['y_mm']:.4f} "
              f"z {f['z_mm']:.4f} mm, rx {f['rx_deg']:.4f} ry {f['ry_deg']:.4f} rz {f['rz_deg']:.4f} deg"
              + ("" if current.stored is None or target.stored is None else
                 f"; the robot program's start frame back to generation {target.stored.generation}"))
        return 0
    finally:
        store.close()


def add_parsers(sub) -> None:
    state_help = "the store's folder (default: $STATE_DIRECTORY, else /var/lib/cellcal)"
    p = sub.add_parser("daemon", help="the service: run routines from the operator panel, write back tool frames",
                       description="Connect the cell's devices, tell systemd it is ready (Type=notify), and serve "
                                   "the operator panel until SIGTERM/SIGINT: a start request runs the selected "
                                   "routine; a tool frame is written back only when every gate passes.")
    p.add_argument("--cell", required=True, metavar="CELL.yaml", help="cell file, or a shipped cell's name")
    p.add_argument("--state-dir", metavar="DIR", help=state_help)
    p.add_argument("--poll-s", type=float, default=0.05, help="panel polling interval (default 0.05 s)")
    p.set_defaults(func=cmd_daemon)

    runs = sub.add_parser("runs", help="the runs recorded in the store").add_subparsers(dest="what", required=True)
    p = runs.add_parser("list", help="the latest runs, newest first")
    p.add_argument("--limit", type=int, default=50)
    p.add_argument("--state-dir", metavar="DIR", help=state_help)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_runs_list)
    p = runs.add_parser("show", help="one run: states, gates, parameters, dataset, report")
    p.add_argument("id", type=int)
    p.add_argument("--state-dir", metavar="DIR", help=state_help)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_runs_show)

    tool = sub.add_parser("tool", help="tool frames written to the controller").add_subparsers(dest="what",
                                                                                              required=True)
    p = tool.add_parser("history", help="every tool frame written or restored")
    p.add_argument("--state-dir", metavar="DIR", help=state_help)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_tool_history)
    p = tool.add_parser("rollback", help="restore the tool frame from before a run's write-back (default: the last)")
    p.add_argument("run", type=int, nargs="?", metavar="RUN")
    p.add_argument("--cell", required=True, metavar="CELL.yaml", help="the cell whose robot gets the frame back")
    p.add_argument("--state-dir", metavar="DIR", help=state_help)
    p.set_defaults(func=cmd_tool_rollback)
