"""Bench: a fleet of cells publishing to one real Mosquitto: messages per second, and the latency from a run's end
to its arrival at a plant consumer.

    python -m bench.plant_bench                        # 20 and 200 cells, 10 runs each
    python -m bench.plant_bench --cells 50 --runs 20

Each cell is what ``cellcal daemon`` runs for the plant (cli/daemon.py ``_publish_to_plant``): its own results
store with the outbox, and its own ``MqttPublisher`` (a paho client and a sender thread); the cells live in
worker processes of GROUP cells each, as threads there (one process per cell is what a plant has; paho's
network loop takes only file descriptors below 1024, which a few hundred stores in one process pass). The runs' ends are written to each store the way the service writes them (``Store.finish_run``,
which queues the run in the same transaction), ``--runs`` per cell, the cells' ends spread evenly over
``--spread`` seconds. A consumer (a persistent QoS 1 subscription to ``plant/#``) takes the time each run
arrives; latency is arrival minus ``finished_at`` (the same clock: one machine). Messages per second: the runs
delivered over the time from the first end to the last arrival.

The baseline, in the same run: one paho client publishing the same number of run messages of the same size
(QoS 1, nothing stored, nothing read back), its rate; the ratio says what the outbox and its bookkeeping
cost against the wire alone. Needs Debian's ``mosquitto`` (``make test`` installs it as root).
"""
from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import paho.mqtt.client as mqtt

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from support.mosquitto import Broker  # noqa: E402  (the suite's broker fixture)

from cellcal.config.cells import MqttSpec  # noqa: E402
from cellcal.daemon.plant_mqtt import MqttPublisher  # noqa: E402
from cellcal.daemon.store import Store  # noqa: E402


class Consumer:
    def __init__(self, port: int):
        self.arrived: dict[tuple[str, int], float] = {}
        self.size = 0
        self.lock = threading.Lock()
        self.client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id="bench-consumer", clean_session=False)
        self.client.on_connect = lambda c, u, f, rc, p=None: c.subscribe("plant/#", qos=1)
        self.client.on_message = self._on_message
        self.client.connect("127.0.0.1", port)
        self.client.loop_start()

    def _on_message(self, client, userdata, msg) -> None:
        now = time.time()
        if "/runs/" not in msg.topic:
            return
        doc = json.loads(msg.payload)
        with self.lock:
            self.arrived.setdefault((doc["topic"], doc["id"]), now - doc["finished_at"])
            self.size = len(msg.payload)

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


GROUP = 25  # cells a worker process holds (each cell's store and socket: paho's select() takes fds below 1024)


def _cells_worker(port: int, folder: str, cells: list[int], n_cells: int, runs: int, t0: float, step: float,
                  done) -> None:
    """One process' share of the fleet: its cells' stores and publishers, their runs ended on the schedule."""
    stores, publishers = {}, []
    for k in cells:
        store = Store.open(Path(folder) / f"cell{k:03d}")
        store.outbox_limit = 10000
        stores[k] = store
        spec = MqttSpec(host="127.0.0.1", port=port, topic=f"plant/line1/cell{k:03d}", client_id=f"c{k}")
        publishers.append(MqttPublisher(spec, Path(folder) / f"cell{k:03d}", f"cell{k:03d}").start())
    for i in range(n_cells * runs):
        if i % n_cells not in stores:
            continue
        delay = t0 + (i + 1) * step - time.time()
        if delay > 0:
            time.sleep(delay)
        store = stores[i % n_cells]
        store.finish_run(store.begin_run("tcp-check", "bench.yaml"), "done", 0, "bench")
    done.wait(180.0)
    for p in publishers:
        p.stop(timeout_s=1.0)
    for s in stores.values():
        s.close()


def fleet(broker: Broker, folder: Path, cells: int, runs: int, spread_s: float) -> dict:
    total = cells * runs
    step = spread_s / total
    t0 = time.time() + 3.0  # every worker up and connected by then
    done = mp.Event()
    workers = [mp.Process(target=_cells_worker, args=(broker.port, str(folder), list(range(g, min(g + GROUP, cells))),
                                                      cells, runs, t0, step, done))
               for g in range(0, cells, GROUP)]
    for w in workers:
        w.start()
    consumer = Consumer(broker.port)
    try:
        deadline = t0 + spread_s + 120.0
        while time.time() < deadline and len(consumer.arrived) < total:
            time.sleep(0.02)
        t_end = time.time()
        latencies = sorted(consumer.arrived.values())
        return {"cells": cells, "runs": total, "arrived": len(latencies), "seconds": t_end - t0,
                "per_s": len(latencies) / (t_end - t0), "message_bytes": consumer.size,
                "latency_median_s": statistics.median(latencies),
                "latency_p95_s": latencies[int(0.95 * (len(latencies) - 1))], "latency_max_s": latencies[-1]}
    finally:
        done.set()
        for w in workers:
            w.join(30.0)
        consumer.close()


def wire_alone(broker: Broker, count: int, size: int) -> float:
    """Messages per second of one paho client publishing `count` QoS 1 messages of `size` bytes."""
    client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id="bench-raw")
    client.max_inflight_messages_set(50)
    client.connect("127.0.0.1", broker.port)
    client.loop_start()
    payload = b"x" * size
    t0 = time.time()
    infos = [client.publish(f"raw/runs/{i}", payload, qos=1) for i in range(count)]
    for info in infos:
        info.wait_for_publish(60.0)
    rate = count / (time.time() - t0)
    client.disconnect()
    client.loop_stop()
    return rate


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cells", type=int, action="append", help="cells in the fleet (repeatable; default 20 and 200)")
    p.add_argument("--runs", type=int, default=10, help="finished runs per cell (default 10)")
    p.add_argument("--spread", type=float, default=10.0, help="seconds over which the runs end (default 10)")
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        for cells in args.cells or (20, 200):
            broker = Broker(Path(tmp) / f"broker{cells}").start()
            try:
                got = fleet(broker, Path(tmp) / f"fleet{cells}", cells, args.runs, args.spread)
                raw = wire_alone(broker, got["runs"], got["message_bytes"])
            finally:
                broker.stop()
            print(f"{cells:4d} cells, {got['runs']} runs ({got['message_bytes']} B each) over {args.spread:g} s: "
                  f"{got['arrived']} arrived, {got['per_s']:.0f} messages/s delivered as they ended; latency "
                  f"median {1000 * got['latency_median_s']:.0f} ms, p95 {1000 * got['latency_p95_s']:.0f} ms, "
                  f"max {1000 * got['latency_max_s']:.0f} ms; the wire alone {raw:.0f} messages/s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
