"""What the OPC UA server (:mod:`.plant_opcua`) serves, kept current from the service and its store.

A thread looks, every POLL_S, at the service's status (``Service.status()``: a fresh dict, safe from any
thread) and at the store's newest finished run. A changed state is handed to ``update_state``; a run that
finished since the last look to ``publish_result`` as the JSON API serves it (``status_api.run_detail``:
the status page, the MQTT message and the OPC UA result read one serializer), in the order the runs
finished. When the service starts, the newest run already finished is the first result: the plant reads
the last result after a restart as before it.
"""
from __future__ import annotations

import json
import logging
import threading
from pathlib import Path

from cellcal.daemon.status_api import ReadOnlyStore, run_detail
from cellcal.daemon.store import StoreError
from cellcal.daemon.store_schema import STORE_FILE

log = logging.getLogger("cellcal.plant")

POLL_S = 0.5


class OpcuaFeed:
    def __init__(self, server, state_dir: str | Path, status):
        self.server, self.state_dir, self.status = server, Path(state_dir), status
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_state = None
        self._last_run: int | None = None

    def start(self) -> "OpcuaFeed":
        self._thread = threading.Thread(target=self._run, name="plant-opcua-feed", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
        self.server.stop()

    def _run(self) -> None:
        store = None
        try:
            while not self._stop.is_set():
                try:
                    state = self.status()
                    key = json.dumps(state, sort_keys=True, default=str)
                    if key != self._last_state:
                        self.server.update_state(state)
                        self._last_state = key
                    store = store or ReadOnlyStore(self.state_dir / STORE_FILE)
                    self._results(store)
                except StoreError as exc:
                    log.warning("OPC UA: the results store cannot be read: %s; retrying", exc)
                    store = None
                self._stop.wait(POLL_S)
        finally:
            if store is not None:
                store.close()

    def _results(self, store: ReadOnlyStore) -> None:
        """The runs finished since the last look, oldest first (at start: the newest alone)."""
        ids = store.finished_after(self._last_run)
        for run_id in ids:
            run = run_detail(store, run_id, self.state_dir)
            if run is not None:
                self.server.publish_result(run)
        if ids:
            self._last_run = ids[-1]
        elif self._last_run is None:
            self._last_run = 0
