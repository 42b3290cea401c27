"""What the status page and its JSON API say (docs/api.md): pure functions from the store's rows
to JSON-able dicts, and the store opened read-only for them.

The server (:mod:`.status_server`) opens the store through a connection of its own for each
request, read-only (``file:...?mode=ro``, ``PRAGMA query_only``): the store is in WAL mode, so
these readers never block the service's writes, and nothing here can change a row. The run
summary has the keys ``cellcal runs list --json`` prints (tests/unit/test_status_api.py keeps
the two the same), plus what a dashboard needs besides: the result code's name, the check's
verdict, the report's URL.
"""
from __future__ import annotations

import json
import math
import sqlite3
import time
from pathlib import Path
from urllib.parse import quote

from cellcal.config.cells import TOOL_IDS
from cellcal.daemon.drift import trend
from cellcal.daemon.service import RESULT_MEANINGS, ResultCode
from cellcal.daemon.store import Store, StoreError
from cellcal.daemon.store_schema import RUN_COLUMNS, SCHEMA_VERSION, STORE_FILE, run_row
from cellcal.routines.framework.base import tool_frame_json

API_VERSION = 1
RUNS_LIMIT = (1, 500)  # /api/v1/runs?limit=N: the bounds of N
RUNS_DEFAULT = 20
REPORTS = "reports"  # STATE/reports: the only folder the server serves files from


class ReadOnlyStore(Store):
    """The results store through a read-only connection of this thread's own. Every reading
    method of :class:`Store` works; a write fails in SQLite (``attempt to write a readonly
    database``), never reaching the file."""

    def __init__(self, path: str | Path):  # noqa: super().__init__ would migrate (write): not called on purpose
        self.path = Path(path)
        try:
            self.db = sqlite3.connect(f"{self.path.resolve().as_uri()}?mode=ro", uri=True, timeout=2.0,
                                      isolation_level=None)
            self.db.execute("PRAGMA query_only = ON")
            version = self.db.execute("PRAGMA user_version").fetchone()[0]
        except sqlite3.Error as exc:
            raise StoreError(f"{self.path}: cannot read the results store: {exc}") from None
        if version != SCHEMA_VERSION:
            self.db.close()
            raise StoreError(f"{self.path}: schema version {version}, this cellcal reads {SCHEMA_VERSION} (the "
                             "service brings it up to date when it starts)")

    def last_verdict(self, tool_id: int) -> dict | None:
        """The newest check of tool `tool_id` that reached a verdict: {"run_id", "verdict", "at"}."""
        row = self.db.execute("SELECT id, verdict, COALESCE(finished_at, started_at) FROM runs WHERE tool_id = ? AND "
                              "verdict IS NOT NULL ORDER BY id DESC LIMIT 1", (int(tool_id),)).fetchone()
        return None if row is None else {"run_id": row[0], "verdict": row[1], "at": row[2]}

    def last_run_of(self, tool_id: int):
        row = self.db.execute(f"SELECT {RUN_COLUMNS} FROM runs WHERE tool_id = ? ORDER BY id DESC LIMIT 1",
                              (int(tool_id),)).fetchone()
        return None if row is None else run_row(row)

    def tool_ids(self) -> set[int]:
        """Every tool id any run, written frame or measured frame names."""
        ids = set()
        for table in ("runs", "tool_frames", "measured_frames"):
            ids.update(r[0] for r in self.db.execute(f"SELECT DISTINCT tool_id FROM {table} WHERE tool_id IS NOT NULL"))
        return {int(i) for i in ids}

    def written_runs(self, run_ids) -> set[int]:
        """Of `run_ids`, the runs whose tool frame was written to the controller (and read back)."""
        run_ids = list(run_ids)
        if not run_ids:
            return set()
        marks = ",".join("?" * len(run_ids))
        return {r[0] for r in self.db.execute(f"SELECT DISTINCT run_id FROM tool_frames WHERE action = 'write' AND "
                                              f"run_id IN ({marks})", run_ids)}


def open_store(state_dir: str | Path) -> ReadOnlyStore | None:
    """The store of `state_dir`, read-only; None when there is none yet (nothing recorded)."""
    path = Path(state_dir) / STORE_FILE
    if not path.is_file():
        return None
    return ReadOnlyStore(path)


# -- builders -----------------------------------------------------------------------------------------


def finite(value):
    """`value` with every float that is not finite made None, recursively: JSON that a browser's
    JSON.parse takes (NaN and Infinity are not JSON)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite(v) for v in value]
    return value


def result_name(code: int | None) -> str | None:
    """``GATE_FAILED`` for 31 (docs/panel.md's result codes); None for no code, the number as text
    for a code this cellcal does not know."""
    if code is None:
        return None
    try:
        return ResultCode(code).name
    except ValueError:
        return str(code)


def report_url(report_path: str | None, state_dir: str | Path) -> str | None:
    """The URL under /reports/ of a report the service wrote into STATE/reports, or None (no
    report, or one elsewhere: the server serves nothing outside that folder)."""
    if not report_path:
        return None
    base = (Path(state_dir) / REPORTS).resolve()
    try:
        rel = Path(report_path).resolve().relative_to(base)
    except (ValueError, OSError):
        return None
    return "/reports/" + quote(rel.as_posix())


def _result(result_json: str | None) -> dict:
    if not result_json:
        return {}
    try:
        out = json.loads(result_json)
    except ValueError:
        return {}
    return out if isinstance(out, dict) else {}


def run_summary(row, written: set[int], state_dir: str | Path) -> dict:
    """One run as /api/v1/runs lists it: ``cellcal runs list --json``'s keys, plus ``result_name``
    (the code's name), ``verdict`` (a check's: ok, corrected, alarm, drift; None for a
    calibration or a run that reached no result) and ``report_url``."""
    return {"id": row.id, "routine": row.routine, "cell": row.cell, "tool_id": row.tool_id,
            "started_at": row.started_at, "finished_at": row.finished_at, "state": row.state,
            "result_code": row.result_code, "result_name": result_name(row.result_code), "reason": row.reason,
            "verdict": row.verdict, "passed_gates": row.passed_gates,
            "written_back": row.id in written, "report_url": report_url(row.report_path, state_dir)}


def runs(store: ReadOnlyStore | None, limit: int, state_dir: str | Path) -> dict:
    """/api/v1/runs: the newest `limit` runs, newest first."""
    if store is None:
        return {"runs": []}
    rows = store.runs(limit)
    written = store.written_runs(r.id for r in rows)
    return finite({"runs": [run_summary(r, written, state_dir) for r in rows]})


def run_detail(store: ReadOnlyStore | None, run_id: int, state_dir: str | Path) -> dict | None:
    """/api/v1/runs/<id>: the summary, its states trail, gates, parameters, result JSON and the
    tool frames it wrote or restored; None when there is no such run."""
    row = None if store is None else store.run(run_id)
    if row is None:
        return None
    out = run_summary(row, store.written_runs([row.id]), state_dir)
    meaning = None
    if row.result_code is not None:
        try:
            meaning = RESULT_MEANINGS.get(ResultCode(row.result_code))
        except ValueError:
            meaning = None
    frames = [_frame_entry(f) for f in store.tool_frames() if f["run_id"] == row.id]
    out.update(result_meaning=meaning,
               states=[{"at": at, "state": s, "message": m} for at, s, m in store.states(row.id)],
               gates=store.gates(row.id), parameters=store.parameters(row.id),
               result=_result(row.result_json) or None, tool_frames=frames)
    return finite(out)


def _frame_entry(f: dict) -> dict:
    """A written or restored tool frame (``cellcal tool history --json``'s row) with the frames
    also in mm and degrees."""
    out = dict(f)
    out["tool_frame"] = tool_frame_json(f["frame_after"])
    out["tool_frame_before"] = None if f["frame_before"] is None else tool_frame_json(f["frame_before"])
    return out


def valid_tool_id(text: str) -> int | None:
    """A tool id from a URL: a whole number of the tool table's range, else None."""
    if not text.isdigit() or len(text) > 3:
        return None
    tool_id = int(text)
    return tool_id if TOOL_IDS[0] <= tool_id <= TOOL_IDS[1] else None


def tools(store: ReadOnlyStore | None, status: dict, names: dict[int, str]) -> dict:
    """/api/v1/tools: every tool of the cell file (`names`: id -> name), the mounted one and
    every tool the store has a run or a frame of, by id: its name, whether it is mounted, the
    last frame written (or restored) for it, the last check's verdict, its last run."""
    mounted = (status or {}).get("mounted_tool") or None
    mounted_id = mounted.get("id") if isinstance(mounted, dict) else None
    ids = set(names) | ({mounted_id} if isinstance(mounted_id, int) else set())
    if store is not None:
        ids |= store.tool_ids()
    out = []
    for tool_id in sorted(ids):
        name = names.get(tool_id) or (mounted.get("name") if tool_id == mounted_id else None)
        last_frame = last_run = verdict = None
        if store is not None:
            frames = store.tool_frames(tool_id)
            last_frame = _frame_entry(frames[-1]) if frames else None
            row = store.last_run_of(tool_id)
            if row is not None:
                last_run = {"id": row.id, "routine": row.routine, "state": row.state, "result_code": row.result_code,
                            "result_name": result_name(row.result_code), "at": row.finished_at or row.started_at}
            verdict = store.last_verdict(tool_id)
        out.append({"id": tool_id, "name": name, "mounted": tool_id == mounted_id, "last_frame": last_frame,
                    "last_verdict": verdict, "last_run": last_run,
                    "history_url": f"/api/v1/tools/{tool_id}/history"})
    return finite({"tools": out})


def tool_history(store: ReadOnlyStore | None, tool_id: int, name: str | None = None,
                 bands: dict | None = None) -> dict:
    """/api/v1/tools/<id>/history: the frames written or restored for the tool (``cellcal tool
    history --json``'s rows), its drift trend (``cellcal tool trend --json``'s object, None
    before any run measured it) and its bands from the cell file (``inner_mm``, ``outer_mm``,
    ``drift_mm`` and the same in deg; None for a tool the cell file no longer has)."""
    frames = [] if store is None else [_frame_entry(f) for f in store.tool_frames(tool_id)]
    measured = [] if store is None else store.measured_frames(tool_id)
    return finite({"tool_id": tool_id, "name": name, "tool_frames": frames,
                   "trend": trend(measured, tool_id) if measured else None, "bands": bands})


def state(status: dict) -> dict:
    """/api/v1/state: the service's own status (``Service.status()``) with the API's version and
    the server's clock."""
    out = dict(status)
    out.update(api=API_VERSION, time=time.time())
    return finite(out)
