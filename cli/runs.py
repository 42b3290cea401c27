"""``cellcal runs list|show``: the runs recorded in the store the daemon keeps."""
from __future__ import annotations

import json
import time

from cellcal.cli.common import STATE_HELP, UsageError, open_store
from cellcal.daemon.service import RESULT_MEANINGS, ResultCode
from cellcal.routines.base import gate_line


def cmd_runs_list(args) -> int:
    store = open_store(args)
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
    store = open_store(args)
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
            print(f"  {gate_line(g)}")
        for key in ("dataset", "report"):
            if out[key]:
                print(f"  {key}: {out[key]}")
        return 0
    finally:
        store.close()


def add_parser(sub) -> None:
    runs = sub.add_parser("runs", help="the runs recorded in the store").add_subparsers(dest="what", required=True)
    p = runs.add_parser("list", help="the latest runs, newest first")
    p.add_argument("--limit", type=int, default=50)
    p.add_argument("--state-dir", metavar="DIR", help=STATE_HELP)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_runs_list)
    p = runs.add_parser("show", help="one run: states, gates, parameters, dataset, report")
    p.add_argument("id", type=int)
    p.add_argument("--state-dir", metavar="DIR", help=STATE_HELP)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_runs_show)
