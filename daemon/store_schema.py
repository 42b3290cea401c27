"""The results store on disk: its files, its tables as the migrations below build them, the
values its columns hold, one row of ``runs`` as the code reads it (:class:`RunRow`), and how a
migration is applied.

The schema is versioned (``PRAGMA user_version``: the number of migrations applied). A store
is brought up to date when it is opened (:class:`cellcal.daemon.store.Store`), each migration
in one transaction of its own, so a process killed mid-migration leaves the store at the last
version it completed. A new store is made by the same migrations, from the first: an old store
and a new one have the same tables, columns and column order.
"""
from __future__ import annotations

import json
import sqlite3
from dataclasses import dataclass, fields

from cellcal.solvers.tool_frames.verdict import Verdict

STORE_FILE = "cellcal.db"
# what the service writes in its state folder besides reports and datasets (cellcal.lock: daemon/claims.py)
STORE_FILES = (STORE_FILE, STORE_FILE + "-wal", STORE_FILE + "-shm", "cellcal.lock")

MIGRATIONS = (
    # 1: runs with their state trail, parameters and gates; tool frames written or restored
    """
    CREATE TABLE runs (
        id INTEGER PRIMARY KEY AUTOINCREMENT,
        routine TEXT NOT NULL,
        cell TEXT NOT NULL,
        started_at REAL NOT NULL,
        finished_at REAL,
        state TEXT NOT NULL,
        result_code INTEGER,
        reason TEXT,
        dataset_path TEXT,
        dataset_sha256 TEXT,
        report_path TEXT,
        write_back INTEGER NOT NULL DEFAULT 0,
        result_json TEXT
    );
    CREATE TABLE states (
        run_id INTEGER NOT NULL REFERENCES runs(id),
        at REAL NOT NULL,
        state TEXT NOT NULL,
        message TEXT
    );
    CREATE TABLE parameters (
        run_id INTEGER NOT NULL REFERENCES runs(id),
        name TEXT NOT NULL, value REAL, std REAL, unit TEXT
    );
    CREATE TABLE gates (
        run_id INTEGER NOT NULL REFERENCES runs(id),
        name TEXT NOT NULL, passed INTEGER NOT NULL, value REAL, limit_value REAL, why TEXT
    );
    CREATE TABLE tool_frames (
        id INTEGER PRIMARY KEY AUTOINCREMENT,
        run_id INTEGER REFERENCES runs(id),
        at REAL NOT NULL,
        action TEXT NOT NULL,
        frame_before TEXT,
        frame_after TEXT NOT NULL
    );
    CREATE INDEX states_by_run ON states(run_id);
    """,
    # 2: events that belong to no run (panel connection lost and back, start-up, shutdown)
    """
    CREATE TABLE events (
        at REAL NOT NULL,
        kind TEXT NOT NULL,
        message TEXT
    );
    """,
    # 3: the tool frame the robot program applies at its start, before and after each write
    """
    ALTER TABLE tool_frames ADD COLUMN stored_before TEXT;
    ALTER TABLE tool_frames ADD COLUMN stored_after TEXT;
    """,
    # 4: the controller's tool frame when each run began (given back after a run that died)
    "ALTER TABLE runs ADD COLUMN tool_frame_before TEXT;",
    # 5: a run that may have left the controller on another tool frame than the one it had
    # before, until that frame is back (or a newer one was written): owed across restarts
    "ALTER TABLE runs ADD COLUMN frame_owed INTEGER NOT NULL DEFAULT 0;",
    # 6: every tool frame a run measured, per tool (calibrations and checks alike, written or
    # not): the tool's drift history (daemon/drift.py, ``cellcal tool trend``)
    """
    CREATE TABLE measured_frames (
        id INTEGER PRIMARY KEY AUTOINCREMENT,
        run_id INTEGER NOT NULL REFERENCES runs(id),
        tool_id INTEGER NOT NULL,
        at REAL NOT NULL,
        kind TEXT NOT NULL,
        routine TEXT NOT NULL,
        frame TEXT NOT NULL,
        determines TEXT NOT NULL,
        written INTEGER NOT NULL DEFAULT 0
    );
    CREATE INDEX measured_frames_by_tool ON measured_frames(tool_id, id);
    """,
    # 7: every run, and every tool frame written or restored, belongs to a tool of the cell's tool
    # table (NULL: a cell that describes no tool). A run before this measured its tool's frame
    # under that tool's id (6), else it was for tool 1, the one tool a file's ``tool`` describes.
    # tool_frames carries the id itself, not through a join on runs: each tool's write history
    # (what ``tool rollback`` walks back) reads from its own index, and a row whose run is gone or
    # was never recorded (run_id NULL) still says whose frame it holds.
    """
    ALTER TABLE runs ADD COLUMN tool_id INTEGER;
    UPDATE runs SET tool_id = COALESCE((SELECT m.tool_id FROM measured_frames m WHERE m.run_id = runs.id
                                        ORDER BY m.id LIMIT 1), 1);
    ALTER TABLE tool_frames ADD COLUMN tool_id INTEGER;
    UPDATE tool_frames SET tool_id = COALESCE((SELECT r.tool_id FROM runs r WHERE r.id = tool_frames.run_id), 1);
    CREATE INDEX tool_frames_by_tool ON tool_frames(tool_id, id);
    CREATE INDEX runs_by_tool ON runs(tool_id, id);
    """,
    # 8: "all gates passed" has one name everywhere (Result.passed_gates, the JSON's passed_gates);
    # written_back, what reached the controller, is the tool_frames' record
    "ALTER TABLE runs RENAME COLUMN write_back TO passed_gates;",
    # 9: a check's verdict (ok, corrected, alarm, drift; NULL for a calibration) read without parsing
    # result_json; an older run's is taken from its result JSON (a JSON string at its top level)
    """
    ALTER TABLE runs ADD COLUMN verdict TEXT;
    UPDATE runs SET verdict = CASE WHEN json_valid(result_json) THEN
        CASE json_type(result_json, '$.verdict') WHEN 'text' THEN json_extract(result_json, '$.verdict') END END
        WHERE result_json IS NOT NULL;
    """,
    # 10: the plant's outbox (docs/plant.md): a finished run queued for the MQTT broker in the transaction that
    # finishes it, delivered in seq order and marked sent on the broker's acknowledgement; one row a run at most;
    # dropped_at: left unpublished when the outbox was full (the run itself stays in runs)
    """
    CREATE TABLE outbox (
        seq INTEGER PRIMARY KEY AUTOINCREMENT,
        run_id INTEGER NOT NULL UNIQUE REFERENCES runs(id),
        queued_at REAL NOT NULL,
        sent_at REAL,
        dropped_at REAL
    );
    CREATE INDEX outbox_pending ON outbox(seq) WHERE sent_at IS NULL AND dropped_at IS NULL;
    """,
)

SCHEMA_VERSION = len(MIGRATIONS)
MEASURED_KINDS = ("calibration", "check")  # measured_frames.kind: a full calibration's frame, or a check's
OPEN_STATES = ("checking", "running", "solving", "gates", "writing back")  # runs.state of a run not ended


@dataclass(frozen=True)
class RunRow:
    """One row of ``runs``."""

    id: int
    routine: str
    cell: str
    started_at: float
    finished_at: float | None
    state: str
    result_code: int | None
    reason: str | None
    dataset_path: str | None
    dataset_sha256: str | None
    report_path: str | None
    passed_gates: bool  # every gate passed: fit to be written back (what was: the tool_frames' writes)
    result_json: str | None
    tool_frame_before: str | None = None
    frame_owed: int = 0
    tool_id: int | None = None  # the tool of the cell's table the run was for (None: the cell has no tool)
    verdict: Verdict | str | None = None  # a check's (None: a calibration or no result); unknown words stay text


_VERDICT_WORDS = frozenset(v.value for v in Verdict)
RUN_COLUMNS = ", ".join(f.name for f in fields(RunRow))  # SELECT RUN_COLUMNS FROM runs: what run_row reads


def run_row(row) -> RunRow:
    """A :class:`RunRow` from a row of ``SELECT RUN_COLUMNS FROM runs``."""
    values = dict(zip((f.name for f in fields(RunRow)), row))
    values["passed_gates"] = bool(values["passed_gates"])
    word = values["verdict"]
    values["verdict"] = Verdict(word) if word in _VERDICT_WORDS else word
    return RunRow(**values)


def tool_id_value(tool_id: int | None) -> int | None:
    """A tool id as stored: a whole number, or NULL for a cell that describes no tool (0 or None)."""
    return None if tool_id is None or int(tool_id) == 0 else int(tool_id)


def json_value(value) -> str | None:
    """A JSON column's value: the JSON text, or NULL for None."""
    return None if value is None else json.dumps(value)


def migrate(db: sqlite3.Connection, number: int) -> None:
    """Migration `number` (0-based: the store's ``user_version`` before it) and the version after
    it, on `db` inside the caller's transaction."""
    for statement in MIGRATIONS[number].split(";"):
        if statement.strip():
            db.execute(statement)
    db.execute(f"PRAGMA user_version = {number + 1}")
