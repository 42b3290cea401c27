"""Stores as an older cellcal made them, and their upgrade when this one opens them.

    with old_store(tmp_path / STORE_FILE, 6) as db:   # migrations 1..6 only, user_version 6
        db.execute("INSERT INTO runs ...")             # rows as that code wrote them
    store = upgraded(tmp_path)                         # opened: every migration since, integrity checked
"""
from __future__ import annotations

import sqlite3
from contextlib import contextmanager
from pathlib import Path

from cellcal.daemon.store import Store
from cellcal.daemon.store_schema import MIGRATIONS, SCHEMA_VERSION


@contextmanager
def old_store(path: Path, version: int):
    """A connection to a new store at `path` with the schema of `version` (its first `version`
    migrations); what was written through it is committed, and it is closed, at the end."""
    db = sqlite3.connect(path)
    try:
        for script in MIGRATIONS[:version]:
            db.executescript(script)
        db.execute(f"PRAGMA user_version = {int(version)}")
        yield db
        db.commit()
    finally:
        db.close()


def upgraded(folder: Path) -> Store:
    """The store of `folder` opened by this cellcal: brought to SCHEMA_VERSION, its integrity intact."""
    store = Store.open(folder)
    assert store.db.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION and store.integrity() == "ok"
    return store
