"""The plant's MQTT side against a real Mosquitto: finished runs arrive in order with the JSON API's keys,
nothing is lost while the broker is down or the service restarts, the will marks a dead service offline, a
full outbox keeps its newest runs, and refused credentials are one log line while the cell works on."""
from __future__ import annotations

import json
from dataclasses import replace
import logging
import time

import pytest

from cellcal.config.cells import MqttSpec
from cellcal.daemon.plant_mqtt import SCHEMA, MqttPublisher
from cellcal.daemon.status_api import ReadOnlyStore, run_detail
from cellcal.daemon.store import Store
from cellcal.daemon.store_schema import STORE_FILE
from support.mosquitto import Broker, DropProxy, Subscriber

TOPIC = "plant/line1/cell7"


def _finish(store: Store, n: int) -> list[int]:
    ids = []
    for _ in range(n):
        run_id = store.begin_run("tcp-check", "cells/cell7.yaml", tool_id=1)
        store.record_state(run_id, "running")
        store.finish_run(run_id, "done", 0, "checked")
        ids.append(run_id)
    return ids


def _spec(port: int, **kw) -> MqttSpec:
    return MqttSpec(host="127.0.0.1", port=port, topic=TOPIC, client_id="cell7", keepalive_s=5, **kw)


@pytest.fixture
def store(tmp_path):
    s = Store.open(tmp_path / "state")
    s.outbox_limit = 1000
    yield s
    s.close()


def test_finished_runs_arrive_in_order_with_the_json_apis_keys(tmp_path, store):
    broker = Broker(tmp_path / "broker").start()
    consumer = Subscriber(broker.port, TOPIC)
    publisher = MqttPublisher(_spec(broker.port), tmp_path / "state", "cell7",
                              status=lambda: {"state": "idle", "health": {"level": "ok"}}).start()
    try:
        ids = _finish(store, 5)
        publisher.notify()
        consumer.wait(lambda: len(consumer.runs()) >= 5 and consumer.states())
        runs = consumer.runs()
        assert [r["id"] for r in runs] == ids
        # the status page's serializer, the same object: the message is /api/v1/runs/<id> plus four keys
        reader = ReadOnlyStore(tmp_path / "state" / STORE_FILE)
        api = run_detail(reader, ids[0], tmp_path / "state")
        reader.close()
        extra = {"cell_name", "topic", "robot", "started_by", "published_at", "schema"}
        assert set(runs[0]) == set(api) | extra
        assert {k: v for k, v in runs[0].items() if k not in extra} == json.loads(json.dumps(api))
        assert runs[0]["schema"] == SCHEMA and runs[0]["topic"] == TOPIC and runs[0]["cell_name"] == "cell7"
        assert runs[0]["started_by"] == "panel"
        state = consumer.states()[-1]
        assert state["online"] and state["state"] == "idle" and state["health"] == "ok"
        consumer.wait(lambda: store.outbox_counts()["sent"] == 5)
        assert store.outbox_counts() == {"pending": 0, "sent": 5, "dropped": 0}
    finally:
        publisher.stop()
        consumer.close()
        broker.stop()


def test_nothing_is_lost_while_the_broker_is_down_and_the_service_restarts(tmp_path, store):
    broker = Broker(tmp_path / "broker").start()
    consumer = Subscriber(broker.port, TOPIC)
    publisher = MqttPublisher(_spec(broker.port), tmp_path / "state", "cell7").start()
    try:
        first = _finish(store, 3)
        publisher.notify()
        consumer.wait(lambda: len(consumer.runs()) >= 3)
        broker.stop()  # the network or the broker away: runs finish all the same, queued in the outbox
        during = _finish(store, 4)
        assert store.outbox_counts()["pending"] == 4
        publisher.stop()  # and the service restarts meanwhile
        publisher = MqttPublisher(_spec(broker.port), tmp_path / "state", "cell7").start()
        later = _finish(store, 2)
        broker.start()
        publisher.notify()
        expected = first + during + later
        consumer.wait(lambda: {r["id"] for r in consumer.runs()} >= set(expected), timeout_s=40.0)
        # at least once on the wire; after dropping repeats of (topic, run id) each run once, in order
        order = [r["id"] for r in consumer.unique_runs()]
        assert order == expected
        consumer.wait(lambda: store.outbox_counts()["pending"] == 0)
        assert store.outbox_counts() == {"pending": 0, "sent": 9, "dropped": 0}
    finally:
        publisher.stop()
        consumer.close()
        broker.stop()


def test_the_last_will_marks_a_dead_service_offline(tmp_path, store):
    broker = Broker(tmp_path / "broker").start()
    consumer = Subscriber(broker.port, TOPIC)
    publisher = MqttPublisher(_spec(broker.port), tmp_path / "state", "cell7",
                              status=lambda: {"state": "idle"}).start()
    try:
        consumer.wait(lambda: any(s["online"] for s in consumer.states()))
        # the service dies: its connection drops without a goodbye (no DISCONNECT), the broker says it for it
        publisher._stop.set()
        publisher.client.loop_stop()
        publisher.client.socket().close()
        consumer.wait(lambda: not consumer.states()[-1]["online"], timeout_s=20.0)
        # and the broker keeps it (retained) for whoever looks later
        late = Subscriber(broker.port, TOPIC, "late")
        late.wait(lambda: late.states())
        assert late.states()[-1]["online"] is False
        late.close()
    finally:
        consumer.close()
        broker.stop()


def test_a_full_outbox_keeps_its_newest_runs_and_counts_the_rest(tmp_path):
    store = Store.open(tmp_path / "state")
    store.outbox_limit = 3
    ids = _finish(store, 5)
    assert [run_id for _, run_id in store.pending()] == ids[2:]
    assert store.outbox_counts() == {"pending": 3, "sent": 0, "dropped": 2}
    assert len(store.runs(10)) == 5  # the runs themselves stay
    store.finish_run(ids[-1], "done", 0, "again")  # a run finished twice is queued once
    assert store.outbox_counts() == {"pending": 3, "sent": 0, "dropped": 2}
    store.close()


def test_refused_credentials_are_one_log_line_and_the_publisher_retries(tmp_path, store, caplog):
    broker = Broker(tmp_path / "broker", users={"cell7": "right"}).start()
    secret = tmp_path / "password"
    secret.write_text("wrong\n")
    secret.chmod(0o600)
    publisher = MqttPublisher(_spec(broker.port, username="cell7", password_file=str(secret)), tmp_path / "state",
                              "cell7")
    caplog.set_level(logging.INFO, logger="cellcal.plant")
    publisher.start()
    try:
        _finish(store, 2)
        deadline = time.monotonic() + 8.0  # the client retries (1 s, then 2 s, ...) while this waits
        while time.monotonic() < deadline and not any("refused" in r.getMessage() for r in caplog.records):
            time.sleep(0.05)
        time.sleep(3.0)
        refused = [r.getMessage() for r in caplog.records if "refused" in r.getMessage()]
        assert len(refused) == 1, refused  # said once, not at every retry
        assert f"127.0.0.1:{broker.port}" in refused[0] and "authori" in refused[0].lower(), refused[0]
        assert store.outbox_counts()["pending"] == 2  # the runs wait, the cell works on
    finally:
        publisher.stop()
        broker.stop()


def test_cellcal_plant_shows_every_cell_on_one_broker(tmp_path, capsys):
    # three cells, each its own store and sender, under one plant topic; `cellcal plant` subscribes to the lot
    from support.cli_run import run_cli

    broker = Broker(tmp_path / "broker").start()
    consumer = Subscriber(broker.port, "plant")  # before the runs: run messages are not retained
    cells, stores = [], []
    try:
        for k in range(3):
            folder = tmp_path / f"cell{k}"
            s = Store.open(folder)
            s.outbox_limit = 100
            stores.append(s)
            spec = MqttSpec(host="127.0.0.1", port=broker.port, topic=f"plant/line1/cell{k}", client_id=f"cell{k}")
            cells.append(MqttPublisher(spec, folder, f"cell{k}", status=lambda k=k: {
                "state": "idle", "health": {"level": "ok"}, "mounted_tool": {"id": k + 1}}).start())
            _finish(s, k + 1)  # cell k has finished k + 1 runs
        consumer.wait(lambda: len(consumer.runs()) >= 6)
        code, out, err = run_cli(capsys, "plant", "--mqtt", f"127.0.0.1:{broker.port}", "--topic", "plant/#",
                                 "--json", "--for", "1")
        assert code == 0, err
        doc = json.loads(out)
        assert [c["topic"] for c in doc["cells"]] == [f"plant/line1/cell{k}" for k in range(3)]
        for k, c in enumerate(doc["cells"]):
            assert c["online"] is True and c["state"] == "idle" and c["health"] == "ok"
            assert c["last_run"]["id"] == k + 1 and c["last_run"]["state"] == "done"  # each store numbers its own
        # nothing there: one message, status 1
        stopped = Broker(tmp_path / "none")
        code, out, err = run_cli(capsys, "plant", "--mqtt", f"127.0.0.1:{stopped.port}", "--json")
        assert code == 1 and "cannot reach the broker" in err and not out
    finally:
        consumer.close()
        for c in cells:
            c.stop()
        for s in stores:
            s.close()
        broker.stop()


def test_a_connection_the_broker_loses_mid_publish_loses_nothing(tmp_path, store):
    # a connection that goes dead mid-stream (what the cell sends is lost, nothing acknowledged) and is then cut,
    # twice: the runs sent into it go again on the next connection, in order, none lost
    broker = Broker(tmp_path / "broker").start()
    relay = DropProxy(broker.port)
    consumer = Subscriber(broker.port, TOPIC)
    publisher = MqttPublisher(_spec(relay.port), tmp_path / "state", "cell7").start()
    ids = []
    try:
        for _ in range(2):
            ids += _finish(store, 50)
            publisher.notify()
            consumer.wait(lambda: {r["id"] for r in consumer.runs()} >= set(ids))
            relay.hold()
            held = _finish(store, 100)
            ids += held
            publisher.notify()
            time.sleep(0.5)  # the sender publishes them into the dead connection
            assert store.outbox_counts()["pending"] == len(held)  # none acknowledged
            relay.drop()
        consumer.wait(lambda: {r["id"] for r in consumer.runs()} >= set(ids), timeout_s=60.0)
        assert [r["id"] for r in consumer.unique_runs()] == ids  # repeats dropped, each run once, in order
        consumer.wait(lambda: store.outbox_counts()["pending"] == 0)
    finally:
        publisher.stop()
        consumer.close()
        relay.close()
        broker.stop()


def test_tls_with_a_client_certificate(tmp_path, store):
    # the broker's listener verifies the cell's certificate; the cell verifies the broker's against the CA
    from support.mosquitto import certificates

    pki = certificates(tmp_path / "pki")
    broker = Broker(tmp_path / "broker", tls={"ca": pki["ca"], "cert": pki["server_cert"],
                                              "key": pki["server_key"]}).start()
    received = []
    spec = _spec(broker.port, tls_ca=pki["ca"], tls_cert=pki["client_cert"], tls_key=pki["client_key"])
    publisher = MqttPublisher(spec, tmp_path / "state", "cell7").start()
    listener = MqttPublisher(replace(spec, client_id="listener"), tmp_path / "state", "x")  # a TLS client to read with
    client = listener.client
    client.on_connect = lambda c, u, f, rc, p=None: c.subscribe(TOPIC + "/runs/#", qos=1)
    client.on_message = lambda c, u, msg: received.append(json.loads(msg.payload)["id"])
    client.will_clear()
    client.connect("127.0.0.1", broker.port)
    client.loop_start()
    try:
        time.sleep(0.5)
        ids = _finish(store, 3)
        publisher.notify()
        deadline = time.monotonic() + 20.0
        while time.monotonic() < deadline and received[:3] != ids:
            time.sleep(0.05)
        assert received[:3] == ids
    finally:
        client.disconnect()
        client.loop_stop()
        publisher.stop()
        broker.stop()
