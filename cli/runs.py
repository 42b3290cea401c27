"""``cellcal runs list|show``: the runs recorded in the store the daemon keeps."""
from __future__ import annotations

import json
import time

from cellcal.cli.common import RECORD_ID, STATE_HELP, UsageError, open_store, whole
from cellcal.daemon.result_codes import RESULT_MEANINGS, ResultCode
from cellcal.daemon.store import file_sha256
from cellcal.routines.framework.base import gate_line


def cmd_runs_list(args) -> int:
    store = open_store(args)
    try:
        runs = store.runs(args.limit)
        if args.json:
            written = _written_back(store)
            print(json.dumps({"runs": [_run_summary(r, written) for r in runs]}))
            return 0
        if not runs:
            print("no runs recorded")
        for r in runs:
            when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(r.started_at))
            code = "" if r.result_code is None else f" code {r.result_code}"
            tool = "-" if r.tool_id is None else str(r.tool_id)
            print(f"{r.id:5d}  {when}  tool {tool:<3} {r.routine:<11} {r.state:<12}{code}  {r.reason or ''}")
        return 0
    finally:
        store.close()


def _written_back(store) -> set[int]:
    """The runs whose tool frame was written to the controller (and read back)."""
    return {f["run_id"] for f in store.tool_frames() if f["action"] == "write"}


def _run_summary(r, written: set[int]) -> dict:
    """``passed_gates``: every quality gate passed, so the result was fit to be written back;
    ``written_back``: its tool frame was written to the controller and read back; ``tool_id``:
    the tool of the cell's tool table the run was for (null: the cell describes no tool)."""
    return {"id": r.id, "routine": r.routine, "cell": r.cell, "tool_id": r.tool_id, "started_at": r.started_at,
            "finished_at": r.finished_at, "state": r.state, "result_code": r.result_code, "reason": r.reason,
            "passed_gates": r.passed_gates, "verdict": None if r.verdict is None else str(r.verdict),
            "written_back": r.id in written}


DATASET_CHECK_TEXT = {"matches": "as recorded: its sha256 matches", "changed": "CHANGED since it was recorded: "
                      "its sha256 no longer matches the store's", "missing": "no longer there",
                      "unreadable": "cannot be read to compare", "not recorded": "no checksum recorded"}


def _dataset_check(r) -> str | None:
    """Whether the run's dataset is still the file recorded: one of DATASET_CHECK_TEXT's keys (None: no dataset)."""
    if not r.dataset_path:
        return None
    if not r.dataset_sha256:
        return "not recorded"
    try:
        return "matches" if file_sha256(r.dataset_path) == r.dataset_sha256 else "changed"
    except FileNotFoundError:
        return "missing"
    except OSError:
        return "unreadable"


def cmd_runs_show(args) -> int:
    store = open_store(args)
    try:
        r = store.run(args.id)
        if r is None:
            raise UsageError(f"no run {args.id} in {store.path}")
        out = _run_summary(r, _written_back(store))
        out.update(dataset=r.dataset_path, dataset_sha256=r.dataset_sha256, dataset_check=_dataset_check(r),
                   report=r.report_path,
                   states=[{"at": at, "state": s, "message": m} for at, s, m in store.states(r.id)],
                   parameters=store.parameters(r.id), gates=store.gates(r.id),
                   result=None if r.result_json is None else json.loads(r.result_json))
        if r.result_code is not None:
            out["result_meaning"] = RESULT_MEANINGS.get(ResultCode(r.result_code), "")
        if args.json:
            print(json.dumps(out))
            return 0
        print(f"run {r.id}: {r.routine} on {r.cell}, {'no tool' if r.tool_id is None else f'tool {r.tool_id}'}: "
              f"{r.state}"
              + ("" if r.result_code is None else f" (code {r.result_code}: {out['result_meaning']})"))
        if r.reason:
            print(f"  {r.reason}")
        if out["written_back"]:
            print("  passed every gate; its tool frame was written back")
        elif r.passed_gates:
            print("  passed every gate; no tool frame written back")
        for s in out["states"]:
            print(f"  {time.strftime('%H:%M:%S', time.localtime(s['at']))}  {s['state']}"
                  + (f": {s['message']}" if s["message"] else ""))
        for g in out["gates"]:
            print(f"  {gate_line(g)}")
        if out["dataset"]:
            print(f"  dataset: {out['dataset']} ({DATASET_CHECK_TEXT[out['dataset_check']]})")
        if out["report"]:
            print(f"  report: {out['report']}")
        return 0
    finally:
        store.close()


def add_parser(sub) -> None:
    runs = sub.add_parser("runs", help="the runs recorded in the store").add_subparsers(dest="what", required=True)
    p = runs.add_parser("list", help="the latest runs, newest first")
    p.add_argument("--limit", type=whole(1, 1_000_000), default=50, metavar="N",
                   help="show at most N runs, 1 .. 1000000 (default 50)")
    p.add_argument("--state-dir", metavar="DIR", help=STATE_HELP)
    p.add_argument("--json", action="store_true", help='print one JSON object on stdout: {"runs": [...]}')
    p.set_defaults(func=cmd_runs_list)
    p = runs.add_parser("show", help="one run: states, gates, parameters, dataset, report")
    p.add_argument("id", type=RECORD_ID, metavar="ID", help="the run's number (cellcal runs list)")
    p.add_argument("--state-dir", metavar="DIR", help=STATE_HELP)
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(func=cmd_runs_show)
