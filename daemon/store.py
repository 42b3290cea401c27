"""The results store: every run, its states, dataset, parameters, gates, the tool frames
written to the controller, and every tool frame a run measured, per tool (the drift history).
SQLite in WAL mode (standard library ``sqlite3``).

Its schema and migrations are :mod:`.store_schema`'s; they are applied, one transaction each,
when the store is opened. Every write is one short transaction, so a process killed at any
moment leaves a store that opens with its integrity intact and every run recorded before the
kill still there; a run the daemon was in the middle of is marked ``interrupted`` when it
next starts.
"""
from __future__ import annotations

import hashlib
import json
import os
import pwd
import sqlite3
import stat
import time
from contextlib import contextmanager
from pathlib import Path

from cellcal.daemon import store_schema
from cellcal.daemon.store_schema import (MEASURED_KINDS, OPEN_STATES, RUN_COLUMNS, SCHEMA_VERSION, STORE_FILE,
                                         STORE_FILES, RunRow, json_value, run_row, tool_id_value)

DEFAULT_STATE_DIR = "/var/lib/cellcal"  # systemd's StateDirectory=cellcal; $STATE_DIRECTORY overrides


def state_dir(override: str | None = None) -> Path:
    """--state-dir, else $STATE_DIRECTORY (systemd), else /var/lib/cellcal."""
    if override:
        return Path(override)
    env = os.environ.get("STATE_DIRECTORY", "").split(":")[0]
    return Path(env or DEFAULT_STATE_DIR)


class StoreError(RuntimeError):
    """The store cannot be opened or is from a newer cellcal."""


def file_sha256(path: str | Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()



def _user(uid: int) -> str:
    try:
        return pwd.getpwuid(uid).pw_name
    except KeyError:
        return str(uid)


def _not_writable(path: Path, folder: Path) -> str:
    """Which file this user cannot write, whose it is, and the command that fixes it."""
    me = _user(os.geteuid())
    try:
        info = path.stat()
        owner = _user(info.st_uid)
        whose = f"it belongs to {owner}, mode {stat.S_IMODE(info.st_mode):04o}"
    except OSError as exc:
        owner, whose = None, f"it cannot be looked at: {exc.strerror or exc}"
    if owner is not None and owner != me:
        fix = f"chown -R {me}: {folder}"
    else:
        fix = f"chmod -R u+rwX {folder}"
    return f"{path} is not writable by user {me} (uid {os.geteuid()}), who runs this service: {whose}; fix: {fix}"


def check_state_folder(folder: str | Path, create: bool = False) -> Path:
    """The state folder (made if missing, with `create`), and every store file in it, writable by
    this user; else StoreError naming the file, its owner and the fix. A store made by another
    user (``cellcal runs list`` as root before the service first started) ends here, at start-up,
    not at the first write of a run."""
    folder = Path(folder)
    if create:
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except FileExistsError:
            raise StoreError(f"{folder}: exists and is not a folder; give --state-dir a folder") from None
        except OSError as exc:
            raise StoreError(f"{folder}: cannot make the state folder ({exc.strerror or exc}); make it and give "
                             f"it to user {_user(os.geteuid())}: mkdir -p {folder} && "
                             f"chown {_user(os.geteuid())}: {folder}") from None
    if not folder.is_dir():
        raise StoreError(f"{folder}: not a folder")
    if not _can(folder, os.W_OK | os.X_OK):
        raise StoreError(_not_writable(folder, folder))
    for name in STORE_FILES:
        path = folder / name
        if path.exists() and not _can(path, os.R_OK | os.W_OK):
            raise StoreError(_not_writable(path, folder))
    return folder


def _is_file(path: Path) -> bool:
    try:
        return path.is_file()
    except OSError as exc:  # a folder on the way this user may not enter
        raise StoreError(f"{path}: cannot look at the results store: {exc.strerror or exc}") from None


def _can(path: Path, mode: int) -> bool:
    """Whether this process (its effective user, as the writes will be) may use `path` so."""
    return os.access(path, mode, effective_ids=os.access in os.supports_effective_ids)


class Store:
    def __init__(self, path: str | Path, create: bool = True):
        """The store at `path`. `create`: make it (and its folder) when missing, and check at once
        that this user can write it (the service); without, a missing store is a StoreError and
        nothing is made (the commands that read it)."""
        self.path = Path(path)
        if create:
            check_state_folder(self.path.parent, create=True)
        elif not _is_file(self.path):
            raise StoreError(f"no results store in {self.path.parent} (nothing recorded there yet, or a typo in "
                             "--state-dir?)")
        try:
            self.db = sqlite3.connect(str(self.path), timeout=10.0, isolation_level=None, check_same_thread=False)
            self.db.execute("PRAGMA journal_mode=WAL")
            self.db.execute("PRAGMA synchronous=FULL")
            self.db.execute("PRAGMA foreign_keys=ON")
            self._migrate()
        except (OSError, sqlite3.Error) as exc:
            raise StoreError(f"{self.path}: cannot open the results store: {exc}") from None
        if create:
            self._probe_write()

    @classmethod
    def open(cls, state_dir_path: str | Path, create: bool = True) -> "Store":
        return cls(Path(state_dir_path) / STORE_FILE, create=create)

    def _probe_write(self) -> None:
        """One write, rolled back: a store this user cannot write fails here, not in a run."""
        try:
            self.db.execute("BEGIN IMMEDIATE")
            try:
                self.db.execute("INSERT INTO events VALUES (0, 'write probe', NULL)")
            finally:
                if self.db.in_transaction:
                    self.db.execute("ROLLBACK")
        except sqlite3.Error as exc:
            self.db.close()
            raise StoreError(f"{_not_writable(self.path, self.path.parent)} ({exc})") from None

    def close(self) -> None:
        self.db.close()

    @contextmanager
    def _tx(self):
        self.db.execute("BEGIN IMMEDIATE")
        try:
            yield self.db
        except BaseException:
            self.db.execute("ROLLBACK")
            raise
        self.db.execute("COMMIT")

    def _migrate(self) -> None:
        version = self.db.execute("PRAGMA user_version").fetchone()[0]
        if version > SCHEMA_VERSION:
            raise StoreError(f"schema version {version} is newer than this cellcal's {SCHEMA_VERSION}")
        for number in range(version, SCHEMA_VERSION):
            with self._tx() as db:
                store_schema.migrate(db, number)

    def integrity(self) -> str:
        return self.db.execute("PRAGMA integrity_check").fetchone()[0]

    # -- runs -----------------------------------------------------------------------------

    def begin_run(self, routine: str, cell: str, tool_id: int | None = 1) -> int:
        """A new run of `routine` on the cell file `cell`, for tool `tool_id` of its tool table
        (default 1: a file's one ``tool``; None: the cell describes no tool), in state checking."""
        now = time.time()
        with self._tx() as db:
            run_id = db.execute("INSERT INTO runs (routine, cell, started_at, state, tool_id) "
                                "VALUES (?, ?, ?, 'checking', ?)",
                                (routine, cell, now, tool_id_value(tool_id))).lastrowid
            db.execute("INSERT INTO states VALUES (?, ?, 'checking', NULL)", (run_id, now))
        return int(run_id)

    def record_run_tool(self, run_id: int, tool_id: int | None) -> None:
        """The tool run `run_id` is for, when it is known only after :meth:`begin_run` (None: none)."""
        with self._tx() as db:
            db.execute("UPDATE runs SET tool_id = ? WHERE id = ?", (tool_id_value(tool_id), run_id))

    def record_state(self, run_id: int, state: str, message: str | None = None) -> None:
        now = time.time()
        with self._tx() as db:
            db.execute("UPDATE runs SET state = ? WHERE id = ?", (state, run_id))
            db.execute("INSERT INTO states VALUES (?, ?, ?, ?)", (run_id, now, state, message))

    def record_result(self, run_id: int, result) -> None:
        """Dataset (path and checksum), parameters, gates, verdict and the result JSON of a solved run."""
        sha = file_sha256(result.dataset) if result.dataset and Path(result.dataset).exists() else None
        verdict = None if result.verdict is None else str(result.verdict)
        with self._tx() as db:
            db.execute("UPDATE runs SET dataset_path = ?, dataset_sha256 = ?, passed_gates = ?, verdict = ?, "
                       "result_json = ? WHERE id = ?", (result.dataset, sha, int(result.passed_gates), verdict,
                                                        result.json_text(), run_id))
            db.executemany("INSERT INTO parameters VALUES (?, ?, ?, ?, ?)",
                           [(run_id, p.name, p.value, p.std, p.unit) for p in result.parameters])
            db.executemany("INSERT INTO gates VALUES (?, ?, ?, ?, ?, ?)",
                           [(run_id, g.name, int(g.passed), g.value, g.limit, g.why) for g in result.gates])

    def record_verdict(self, run_id: int, verdict) -> None:
        """A check's verdict when it ended without a result to record (a sweep that missed the
        beams is an alarm before anything could be solved)."""
        with self._tx() as db:
            db.execute("UPDATE runs SET verdict = ? WHERE id = ?", (str(verdict), run_id))

    def record_report(self, run_id: int, report_path: str) -> None:
        with self._tx() as db:
            db.execute("UPDATE runs SET report_path = ? WHERE id = ?", (report_path, run_id))

    def finish_run(self, run_id: int, state: str, result_code: int, reason: str | None = None) -> None:
        """The run's end; with an outbox (``outbox_limit``), the run queued for the plant in the same transaction."""
        now = time.time()
        with self._tx() as db:
            db.execute("UPDATE runs SET state = ?, result_code = ?, reason = ?, finished_at = ? WHERE id = ?",
                       (state, result_code, reason, now, run_id))
            db.execute("INSERT INTO states VALUES (?, ?, ?, ?)", (run_id, now, state, reason))
            if self.outbox_limit:
                self._queue(db, run_id, now)

    # -- the plant's outbox (daemon/plant_mqtt.py) ------------------------------------------

    outbox_limit: int | None = None  # set when the cell publishes to a broker: finished runs are queued, this many

    def _queue(self, db, run_id: int, now: float) -> None:
        """Queue a finished run (once: a run id has one row), and leave the oldest unpublished beyond the limit."""
        db.execute("INSERT OR IGNORE INTO outbox (run_id, queued_at) VALUES (?, ?)", (run_id, now))
        over = db.execute("SELECT COUNT(*) FROM outbox WHERE sent_at IS NULL AND dropped_at IS NULL").fetchone()[0] \
            - int(self.outbox_limit)
        if over > 0:
            db.execute("UPDATE outbox SET dropped_at = ? WHERE seq IN (SELECT seq FROM outbox WHERE sent_at IS NULL "
                       "AND dropped_at IS NULL ORDER BY seq LIMIT ?)", (now, over))

    def pending(self, limit: int = 100) -> list[tuple[int, int]]:
        """(seq, run id) of the runs queued and not yet delivered, oldest first, at most `limit`."""
        return [(int(a), int(b)) for a, b in self.db.execute(
            "SELECT seq, run_id FROM outbox WHERE sent_at IS NULL AND dropped_at IS NULL ORDER BY seq LIMIT ?",
            (int(limit),))]

    def delivered(self, seqs) -> None:
        """Mark queued runs sent (the broker acknowledged them)."""
        now = time.time()
        with self._tx() as db:
            db.executemany("UPDATE outbox SET sent_at = ? WHERE seq = ? AND sent_at IS NULL",
                           [(now, int(s)) for s in seqs])

    def outbox_counts(self) -> dict:
        """{"pending", "sent", "dropped"}: the outbox's runs by what became of them."""
        row = self.db.execute("SELECT COALESCE(SUM(sent_at IS NULL AND dropped_at IS NULL), 0), "
                              "COALESCE(SUM(sent_at IS NOT NULL), 0), COALESCE(SUM(dropped_at IS NOT NULL), 0) "
                              "FROM outbox").fetchone()
        return {"pending": int(row[0]), "sent": int(row[1]), "dropped": int(row[2])}

    def record_frame_before(self, run_id: int, frame) -> None:
        with self._tx() as db:
            db.execute("UPDATE runs SET tool_frame_before = ? WHERE id = ?",
                       (json.dumps([float(v) for v in frame]), run_id))

    def owe_frame(self, run_id: int, frame) -> None:
        """The controller's tool frame as run `run_id` began, owed back to it from now on
        (the routines put the tool as drawn on the controller while they measure)."""
        with self._tx() as db:
            db.execute("UPDATE runs SET tool_frame_before = ?, frame_owed = 1 WHERE id = ?",
                       (json.dumps([float(v) for v in frame]), run_id))

    def frame_settled(self, run_id: int) -> None:
        """The controller has the frame owed for `run_id`, or a newer one (a write-back of
        this run or a later one, a rollback): nothing from `run_id` or before is owed any more."""
        with self._tx() as db:
            db.execute("UPDATE runs SET frame_owed = 0 WHERE id <= ? AND frame_owed = 1", (run_id,))

    def owed_frame(self) -> tuple[int, list[float]] | None:
        """(run id, frame) the controller is still owed, or None. Only the newest run can owe
        one (the service starts no run while a frame is owed); a frame owed from before a
        tool frame was written (write-back, rollback) is stale and never comes back."""
        row = self.db.execute("SELECT id, started_at, tool_frame_before, tool_id FROM runs WHERE frame_owed = 1 "
                              "ORDER BY id DESC LIMIT 1").fetchone()
        if row is None:
            return None
        run_id, started_at, frame, tool_id = row
        # a frame written since for another tool went to that tool's block only (it was not
        # mounted): the running frame owed is still the owing run's tool's
        newer = self.db.execute("SELECT COUNT(*) FROM tool_frames WHERE (run_id > ? OR at > ?) "
                                "AND (tool_id IS ? OR tool_id IS NULL OR ? IS NULL)",
                                (run_id, started_at, tool_id, tool_id)).fetchone()[0]
        if newer or frame is None:
            self.frame_settled(run_id)
            return None
        return int(run_id), json.loads(frame)

    def mark_interrupted(self, result_code: int) -> list[int]:
        """Runs a previous process left open (it died mid-run): recorded as interrupted."""
        open_runs = [r[0] for r in self.db.execute(
            f"SELECT id FROM runs WHERE state IN ({','.join('?' * len(OPEN_STATES))})", OPEN_STATES)]
        for run_id in open_runs:
            self.finish_run(run_id, "interrupted", result_code,
                            "the daemon stopped during this run (killed or crashed); nothing was written back")
        return open_runs

    def last_passed_result(self, routine: str, tool_id: int | None = None) -> tuple[int, dict] | None:
        """(run id, result JSON) of the newest run of `routine` (for tool `tool_id`; None: any
        tool) that passed every gate and ended done, or None."""
        row = self.db.execute("SELECT id, result_json FROM runs WHERE routine = ? AND state = 'done' AND "
                              "passed_gates = 1 AND result_json IS NOT NULL AND (? IS NULL OR tool_id = ?) "
                              "ORDER BY id DESC LIMIT 1", (routine, tool_id, tool_id)).fetchone()
        return None if row is None else (int(row[0]), json.loads(row[1]))

    def runs(self, limit: int = 50) -> list[RunRow]:
        rows = self.db.execute(f"SELECT {RUN_COLUMNS} FROM runs ORDER BY id DESC LIMIT ?", (limit,)).fetchall()
        return [run_row(r) for r in rows]

    def finished_after(self, run_id: int | None) -> list[int]:
        """Ids of the runs finished with an id above run_id, oldest first; None: the newest finished run alone."""
        if run_id is None:
            row = self.db.execute("SELECT id FROM runs WHERE finished_at IS NOT NULL ORDER BY id DESC LIMIT 1")
            return [int(r[0]) for r in row]
        return [int(r[0]) for r in self.db.execute(
            "SELECT id FROM runs WHERE finished_at IS NOT NULL AND id > ? ORDER BY id", (int(run_id),))]

    def run(self, run_id: int) -> RunRow | None:
        row = self.db.execute(f"SELECT {RUN_COLUMNS} FROM runs WHERE id = ?", (run_id,)).fetchone()
        return None if row is None else run_row(row)

    def states(self, run_id: int) -> list[tuple[float, str, str | None]]:
        return [tuple(r) for r in self.db.execute("SELECT at, state, message FROM states WHERE run_id = ? "
                                                 "ORDER BY rowid", (run_id,))]

    def gates(self, run_id: int) -> list[dict]:
        return [{"name": n, "passed": bool(p), "value": v, "limit": lim, "why": w} for n, p, v, lim, w in
                self.db.execute("SELECT name, passed, value, limit_value, why FROM gates WHERE run_id = ?",
                                (run_id,))]

    def parameters(self, run_id: int) -> list[dict]:
        return [{"name": n, "value": v, "std": s, "unit": u} for n, v, s, u in
                self.db.execute("SELECT name, value, std, unit FROM parameters WHERE run_id = ?", (run_id,))]

    # -- tool frames ----------------------------------------------------------------------

    def record_tool_frame(self, run_id: int | None, action: str, before, after, stored_before: dict | None = None,
                          stored_after: dict | None = None, tool_id: int | None = None) -> None:
        """A tool frame written (``before`` -> ``after``); ``stored_*`` the frame the robot program
        applies at its start ({"tool_frame", "generation"}), None where the robot keeps none.
        It is the frame of tool `tool_id`; None: of run `run_id`'s tool (a write-back is its own
        run's tool, a rollback the tool of the run it undoes)."""
        with self._tx() as db:
            if tool_id is None and run_id is not None:
                row = db.execute("SELECT tool_id FROM runs WHERE id = ?", (run_id,)).fetchone()
                tool_id = None if row is None else row[0]
            db.execute("INSERT INTO tool_frames (run_id, at, action, frame_before, frame_after, stored_before, "
                       "stored_after, tool_id) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                       (run_id, time.time(), action, None if before is None else json.dumps(list(map(float, before))),
                        json.dumps(list(map(float, after))), json_value(stored_before), json_value(stored_after),
                        tool_id_value(tool_id)))

    def tool_frames(self, tool_id: int | None = None) -> list[dict]:
        """Every tool frame written or restored, oldest first (of tool `tool_id`; None: of every
        tool): {"id", "run_id", "tool_id", "at", "action", "frame_before", "frame_after",
        "stored_before", "stored_after"}."""
        return [{"id": i, "run_id": r, "tool_id": t, "at": at, "action": a,
                 "frame_before": None if b is None else json.loads(b), "frame_after": json.loads(f),
                 "stored_before": None if sb is None else json.loads(sb),
                 "stored_after": None if sa is None else json.loads(sa)}
                for i, r, t, at, a, b, f, sb, sa in self.db.execute(
                    "SELECT id, run_id, tool_id, at, action, frame_before, frame_after, stored_before, stored_after "
                    "FROM tool_frames WHERE ? IS NULL OR tool_id = ? ORDER BY id", (tool_id, tool_id))]

    def writes_not_undone(self, tool_id: int | None = None) -> list[dict]:
        """The write-backs still in effect, oldest first: what ``tool rollback`` can undo (of tool
        `tool_id`; None: of every tool, each tool's walked on its own).

        Each tool has its own frame on the controller, so its history is its own: a rollback of
        run R put R's tool back where it was before R's write, so it undoes R's write and every
        write of that tool recorded after it (another tool's writes stay); the last entry of a
        tool's list is what a rollback of that tool without a run undoes next (repeated, they
        walk back through that tool's history)."""
        active: dict[int | None, list[dict]] = {}
        for frame in self.tool_frames(tool_id):
            mine = active.setdefault(frame["tool_id"], [])
            if frame["action"] == "write" and frame["frame_before"] is not None:
                mine.append(frame)
            elif frame["action"] == "rollback":
                undone = next((k for k, w in enumerate(mine) if w["run_id"] == frame["run_id"]), None)
                if undone is not None:
                    del mine[undone:]
        return sorted((w for writes in active.values() for w in writes), key=lambda w: w["id"])

    # -- measured tool frames (the drift history) -------------------------------------------

    def record_measured_frame(self, run_id: int, tool_id: int, kind: str, routine: str, frame, determines,
                              written: bool = False, at: float | None = None) -> None:
        """The tool frame run `run_id` measured for tool `tool_id` ([x, y, z, rx, ry, rz], m and
        rad, flange frame): `kind` "calibration" or "check", what of it was `determines`d
        ("tip", "axis"), whether it was written to the controller (:meth:`measured_frame_written`
        marks it later)."""
        if kind not in MEASURED_KINDS:
            raise ValueError(f"kind {kind!r} is none of {', '.join(MEASURED_KINDS)}")
        with self._tx() as db:
            db.execute("INSERT INTO measured_frames (run_id, tool_id, at, kind, routine, frame, determines, written) "
                       "VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                       (run_id, int(tool_id), time.time() if at is None else float(at), kind, routine,
                        json.dumps([float(v) for v in frame]), json.dumps(sorted(determines)), int(written)))

    def measured_frame_written(self, run_id: int) -> None:
        """Run `run_id`'s measured frame went to the controller (its write-back passed)."""
        with self._tx() as db:
            db.execute("UPDATE measured_frames SET written = 1 WHERE run_id = ?", (run_id,))

    def measured_frames(self, tool_id: int) -> list[dict]:
        """Every tool frame measured for `tool_id`, oldest first: {"run_id", "tool_id", "at",
        "kind", "routine", "frame" (m, rad), "determines" (list), "written" (bool)}."""
        return [{"run_id": r, "tool_id": t, "at": at, "kind": k, "routine": rt, "frame": json.loads(f),
                 "determines": json.loads(d), "written": bool(w)}
                for r, t, at, k, rt, f, d, w in self.db.execute(
                    "SELECT run_id, tool_id, at, kind, routine, frame, determines, written FROM measured_frames "
                    "WHERE tool_id = ? ORDER BY id", (int(tool_id),))]

    def measured_tools(self) -> list[int]:
        """The tool ids with at least one measured frame."""
        return [int(r[0]) for r in self.db.execute("SELECT DISTINCT tool_id FROM measured_frames ORDER BY tool_id")]

    # -- events ---------------------------------------------------------------------------

    def event(self, kind: str, message: str | None = None) -> None:
        with self._tx() as db:
            db.execute("INSERT INTO events VALUES (?, ?, ?)", (time.time(), kind, message))

    def events(self) -> list[tuple[float, str, str | None]]:
        return [tuple(r) for r in self.db.execute("SELECT at, kind, message FROM events ORDER BY rowid")]
