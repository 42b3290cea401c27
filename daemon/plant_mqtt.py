"""Publishing to the plant's MQTT broker (the cell file's ``plant: mqtt:``; docs/plant.md).

Under the cell's topic T:

- ``T/state`` (retained, QoS 1): the service's state, device health, mounted tool and the run under
  way, published when it changes; the broker's copy is the newest. The connection's last will
  publishes ``{"online": false}`` there (retained) when the service dies without saying goodbye; a
  clean stop publishes it itself.
- ``T/runs/<run id>`` (QoS 1, not retained): one JSON object per finished run, the keys of the JSON
  API's ``/api/v1/runs/<id>`` (``status_api.run_detail``: the status page and the plant read one
  serializer) plus ``cell_name``, ``topic``, ``robot``, ``started_by``, ``published_at`` and ``schema``.

Store-and-forward. A finished run is queued in the store's outbox in the transaction that
finishes it (``Store.finish_run``); the sender here delivers the outbox in order, a window of
runs at a time, and marks each sent when the broker acknowledges it (PUBACK). Whatever was not
acknowledged when the connection dropped, or when the service stopped, is sent again after the
reconnect or the restart: at least once on the wire, each run once in the outbox's bookkeeping.
Consumers drop repeats by (topic, run id). A full outbox leaves its oldest runs unpublished
(``Store.outbox_limit``; they stay in the store, counted as dropped in ``T/state``).

The broker refusing the connection (credentials, not authorised) or being away is one log line
naming the broker and the reason, each time the reason changes; the client retries with back-off
(1 s doubling to 60 s) and the cell works on meanwhile.
"""
from __future__ import annotations

import json
import logging
import ssl
import threading
import time
from pathlib import Path

import paho.mqtt.client as mqtt

from cellcal.config.cells import MqttSpec
from cellcal.daemon.status_api import ReadOnlyStore, finite, run_detail, run_summary
from cellcal.daemon.store import Store, StoreError
from cellcal.daemon.store_schema import STORE_FILE

log = logging.getLogger("cellcal.plant")

SCHEMA = "cellcal.run/1"  # the run message's schema (docs/plant.md); STATE_SCHEMA the state message's
STATE_SCHEMA = "cellcal.state/1"
WINDOW = 50  # runs published before waiting for their acknowledgements
ACK_WAIT_S = 10.0  # how long a window waits for its acknowledgements before it is sent again
STATE_POLL_S = 0.5  # how often the service's state is looked at for a change
RETRY_S = (1.0, 60.0)  # the reconnect back-off: first and longest wait


def run_message(store: ReadOnlyStore, run_id: int, state_dir, cell_name: str, topic: str,
                robot: str | None = None) -> dict | None:
    """The message of one finished run: ``run_detail`` (what ``/api/v1/runs/<id>`` serves) plus the cell's
    name, its topic, the robot model, what started it (the service runs what the panel starts), the time of
    publishing and the schema; None when the store has no such run."""
    doc = run_detail(store, run_id, state_dir)
    if doc is None:
        return None
    return {**doc, "cell_name": cell_name, "topic": topic, "robot": robot, "started_by": "panel",
            "published_at": time.time(), "schema": SCHEMA}


def state_message(status: dict, cell_name: str, outbox: dict | None, online: bool = True,
                  last_run: dict | None = None) -> dict:
    """``T/state``: what the status page's headline says (state, health, mounted tool, run under way, the
    devices), whether the service is online, what became of the outbox's runs, and the last finished run's
    summary (``status_api.run_summary``: a consumer that subscribes late sees the last result at once)."""
    status = status or {}
    health = status.get("health")
    return finite({"cell_name": cell_name, "online": online, "state": status.get("state"),
                   "health": health.get("level") if isinstance(health, dict) else health,
                   "mounted_tool": status.get("mounted_tool"), "run": status.get("run_id"),
                   "devices": status.get("devices"), "outbox": outbox, "last_run": last_run,
                   "published_at": time.time(), "schema": STATE_SCHEMA})


def last_finished(store: ReadOnlyStore, state_dir) -> dict | None:
    """The newest finished run's summary (what ``/api/v1/runs`` lists for it), None before any."""
    newest = store.finished_after(None)
    if not newest:
        return None
    row = store.run(newest[0])
    return run_summary(row, store.written_runs([row.id]), state_dir)


class MqttPublisher:
    """The sender: a paho client (its own network thread) and a thread that delivers the outbox and the
    state. ``start`` returns at once; the broker may come later."""

    def __init__(self, spec: MqttSpec, state_dir: str | Path, cell_name: str, status=None, robot: str | None = None):
        self.spec, self.state_dir, self.cell_name, self.robot = spec, Path(state_dir), cell_name, robot
        self.status = status or (lambda: {})
        self.topic = spec.topic
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._connected = threading.Event()
        self._lock = threading.Lock()
        self._acked: set[int] = set()  # message ids the broker acknowledged
        self._said = None  # the last connection problem logged (each said once until it changes)
        self._thread: threading.Thread | None = None
        self.client = self._client()

    # -- the connection ---------------------------------------------------------------------

    def _client(self) -> mqtt.Client:
        spec = self.spec
        client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=spec.client_id, clean_session=True)
        if spec.username is not None:
            password = None
            if spec.password_file is not None:
                password = Path(spec.password_file).read_text().rstrip("\r\n")
            client.username_pw_set(spec.username, password)
        if spec.tls_ca is not None or spec.tls_cert is not None:
            client.tls_set(ca_certs=spec.tls_ca, certfile=spec.tls_cert, keyfile=spec.tls_key,
                           cert_reqs=ssl.CERT_REQUIRED, tls_version=ssl.PROTOCOL_TLS_CLIENT)
        client.will_set(self.topic + "/state", json.dumps(state_message({}, self.cell_name, None, online=False)),
                        qos=1, retain=True)
        client.reconnect_delay_set(min_delay=int(RETRY_S[0]), max_delay=int(RETRY_S[1]))
        client.on_connect = self._on_connect
        client.on_disconnect = self._on_disconnect
        client.on_publish = self._on_publish
        client.enable_logger(logging.getLogger("cellcal.plant.paho"))
        return client

    def _broker(self) -> str:
        return f"MQTT broker {self.spec.host}:{self.spec.port}"

    def _say(self, level, text: str) -> None:
        if text != self._said:
            self._said = text
            log.log(level, text)

    def _on_connect(self, client, userdata, flags, reason_code, properties=None) -> None:
        if reason_code.is_failure:
            self._say(logging.ERROR, f"{self._broker()} refused the connection: {reason_code}; retrying (the cell "
                                     "works on, finished runs wait in the outbox)")
            return
        self._say(logging.INFO, f"{self._broker()}: connected, publishing under {self.topic}")
        self._connected.set()
        self._last_state = None  # the broker may have lost the retained state: say it again
        self._wake.set()

    def _on_disconnect(self, client, userdata, flags, reason_code, properties=None) -> None:
        was = self._connected.is_set()  # a refused connection ends too: said by _on_connect already
        self._connected.clear()
        if was and not self._stop.is_set():
            self._say(logging.WARNING, f"{self._broker()}: connection lost ({reason_code}); retrying (finished runs "
                                       "wait in the outbox)")

    def _on_publish(self, client, userdata, mid, reason_code=None, properties=None) -> None:
        with self._lock:
            self._acked.add(mid)
        self._wake.set()

    # -- the service's side -----------------------------------------------------------------

    def start(self) -> "MqttPublisher":
        self._last_state = None
        try:
            self.client.connect_async(self.spec.host, self.spec.port, keepalive=self.spec.keepalive_s)
        except (OSError, ValueError) as exc:  # a host name that does not resolve: the loop retries it
            self._say(logging.ERROR, f"{self._broker()}: {exc}; retrying")
        self.client.loop_start()
        self._thread = threading.Thread(target=self._run, name="plant-mqtt", daemon=True)
        self._thread.start()
        return self

    def notify(self) -> None:
        """A run finished (or the state changed): look at the outbox now rather than at the next poll."""
        self._wake.set()

    def stop(self, timeout_s: float = 5.0) -> None:
        """Say offline (retained), flush what can be flushed within timeout_s, disconnect."""
        if self._stop.is_set():
            return
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
        if self._connected.is_set():
            info = self.client.publish(self.topic + "/state", json.dumps(
                state_message(self.status(), self.cell_name, None, online=False)), qos=1, retain=True)
            try:
                info.wait_for_publish(timeout=min(timeout_s, 2.0))
            except (RuntimeError, ValueError):
                pass
            self.client.disconnect()
        self.client.loop_stop()

    # -- the sender -------------------------------------------------------------------------

    def _run(self) -> None:
        store = reader = None
        try:
            while not self._stop.is_set():
                self._wake.wait(STATE_POLL_S)
                self._wake.clear()
                if not self._connected.is_set():
                    continue
                try:
                    if store is None:
                        store = Store(self.state_dir / STORE_FILE, create=False)
                        reader = ReadOnlyStore(self.state_dir / STORE_FILE)
                    self._publish_state(store, reader)
                    while self._connected.is_set() and not self._stop.is_set() and self._deliver(store, reader):
                        pass
                except StoreError as exc:
                    self._say(logging.ERROR, f"plant: the results store cannot be read: {exc}; retrying")
                    store = reader = None
        finally:
            for s in (store, reader):
                if s is not None:
                    s.close()

    def _publish_state(self, store: Store, reader: ReadOnlyStore) -> None:
        doc = state_message(self.status(), self.cell_name, store.outbox_counts(),
                            last_run=last_finished(reader, self.state_dir))
        key = json.dumps({k: v for k, v in doc.items() if k != "published_at"}, sort_keys=True, default=str)
        if key == self._last_state:
            return
        self.client.publish(self.topic + "/state", json.dumps(doc), qos=1, retain=True)
        self._last_state = key

    def _deliver(self, store: Store, reader: ReadOnlyStore) -> bool:
        """One window of the outbox, in order, waited for; True when it was all acknowledged and more may wait."""
        batch = store.pending(WINDOW)
        if not batch:
            return False
        with self._lock:  # acknowledgements of a window given up on: their message ids will be reused
            self._acked.clear()
        sent: list[tuple[int, int]] = []  # (seq, mid)
        for seq, run_id in batch:
            message = run_message(reader, run_id, self.state_dir, self.cell_name, self.topic, self.robot)
            if message is None:  # the run is gone from the store (it never is, but nothing to send)
                store.delivered([seq])
                continue
            info = self.client.publish(f"{self.topic}/runs/{run_id}", json.dumps(message), qos=1)
            if info.rc != mqtt.MQTT_ERR_SUCCESS:
                break  # not connected any more: the rest waits for the reconnect
            sent.append((seq, info.mid))
        deadline = time.monotonic() + ACK_WAIT_S
        done: list[int] = []
        while sent and time.monotonic() < deadline and not self._stop.is_set():
            with self._lock:
                acked = [seq for seq, mid in sent if mid in self._acked]
                self._acked.difference_update(mid for seq, mid in sent if seq in acked)
            if acked:
                store.delivered(acked)
                done += acked
                sent = [(seq, mid) for seq, mid in sent if seq not in acked]
            if not sent or not self._connected.is_set():
                break
            self._wake.wait(0.05)
            self._wake.clear()
        return not sent and len(done) == len(batch)
