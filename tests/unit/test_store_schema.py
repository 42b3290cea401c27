"""The store's schema (daemon/store_schema.py): migration 8 renames ``runs.write_back`` to
``passed_gates`` (every gate passed; what reached the controller is ``written_back``, the
tool_frames' record), migration 9 adds ``runs.verdict`` and fills it for the runs recorded
before from their result JSON; a new store has the columns an upgraded one has, and the
store writes and reads the verdict as a :class:`Verdict`.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cellcal.daemon import status_api
from cellcal.daemon.store import Store
from cellcal.daemon.store_schema import STORE_FILE
from cellcal.routines.framework.base import Gate, Result
from cellcal.solvers.tool_frames.verdict import Verdict
from support.old_stores import old_store, upgraded  # tests/support/old_stores.py

# (routine, write_back, result_json) as the schema-7 code recorded them, and the verdict each reads after
SCHEMA_7_RUNS = (
    ("tcp-laser", 1, json.dumps({"routine": "tcp-laser", "passed_gates": True}), None),
    ("tcp-check", 0, json.dumps({"routine": "tcp-check", "passed_gates": True, "verdict": "drift"}), Verdict.DRIFT),
    ("tcp-check", 1, json.dumps({"routine": "tcp-check", "verdict": "ok", "notes": ["\"verdict\": x"]}), Verdict.OK),
    ("tcp-check", 0, json.dumps({"routine": "tcp-check", "verdict": None}), None),
    ("tcp-check", 0, json.dumps(["verdict", "alarm"]), None),  # JSON, but no object
    ("tcp-check", 0, "not json", None),
    ("identify", 0, None, None),  # a run that reached no result
)


def columns(db) -> list[str]:
    return [r[1] for r in db.execute("PRAGMA table_info(runs)")]


@pytest.fixture
def schema_7(tmp_path) -> Path:
    """A state folder whose store the schema-7 code made, with SCHEMA_7_RUNS in it as it wrote them."""
    with old_store(tmp_path / STORE_FILE, 7) as db:
        db.executemany("INSERT INTO runs (routine, cell, started_at, state, write_back, result_json, tool_id) "
                       "VALUES (?, 'sim', 1.0, 'done', ?, ?, 1)", [run[:3] for run in SCHEMA_7_RUNS])
    return tmp_path


def test_a_schema_7_store_gets_passed_gates_and_the_verdicts_of_its_old_runs(schema_7):
    store = upgraded(schema_7)
    try:
        assert "write_back" not in columns(store.db) and {"passed_gates", "verdict"} <= set(columns(store.db))
        rows = sorted(store.runs(), key=lambda r: r.id)
        assert [r.passed_gates for r in rows] == [bool(w) for _, w, _, _ in SCHEMA_7_RUNS]
        assert [r.verdict for r in rows] == [v for _, _, _, v in SCHEMA_7_RUNS]
        assert all(r.verdict is None or type(r.verdict) is Verdict for r in rows)
        assert [r.result_json for r in rows] == [j for _, _, j, _ in SCHEMA_7_RUNS]  # the JSON as it was
        assert store.last_passed_result("tcp-laser")[0] == 1  # it reads the renamed column
    finally:
        store.close()
    ro = status_api.open_store(schema_7)  # the status API reads the filled column, not the JSON
    try:
        assert ro.last_verdict(1)["run_id"] == 3 and ro.last_verdict(1)["verdict"] == "ok"
    finally:
        ro.close()


def test_a_new_store_has_the_columns_of_an_upgraded_one_in_the_same_order(schema_7, tmp_path):
    old, new = Store.open(schema_7), Store(tmp_path / "new" / STORE_FILE)
    try:
        assert columns(old.db) == columns(new.db)
    finally:
        old.close()
        new.close()


def test_the_store_records_a_checks_verdict_and_reads_it_back_as_a_verdict(tmp_path):
    store = Store.open(tmp_path)
    try:
        result = Result("tcp-check", [], np.zeros(3), 0.01, 1.0, [Gate("residual", True, 0.01, 0.05, "within")],
                        tool_frame=np.array([0.0, 0.0, 0.15, 0.0, 0.0, 0.0]), determines=frozenset({"tip"}),
                        verdict="corrected")
        check, calibration = store.begin_run("tcp-check", "sim"), store.begin_run("tcp-npoint", "sim")
        store.record_result(check, result)
        store.record_result(calibration, Result("tcp-npoint", [], np.zeros(3), 0.01, 1.0, []))
        assert store.run(check).verdict is Verdict.CORRECTED and store.run(check).passed_gates is True
        assert json.loads(store.run(check).result_json)["verdict"] == "corrected"
        assert store.run(calibration).verdict is None and store.run(calibration).passed_gates is False
        assert store.db.execute("SELECT verdict FROM runs WHERE id = ?", (check,)).fetchone()[0] == "corrected"
    finally:
        store.close()
