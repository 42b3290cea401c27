"""The chain to the plant: ``cellcal daemon`` on the networked simulated cell, its cell file publishing to a real
Mosquitto, runs started from the panel; a plant consumer receives each finished run (what the JSON API serves
for it) and the service's state, and a broker that goes away meanwhile loses nothing."""
from __future__ import annotations

import asyncio
import time

from support.daemon_harness import SUITE_TIME_SCALE, Daemon, Net, one_run, short_cell
from support.cell_edits import edited_cell
from support.mosquitto import Broker, Subscriber, free_port

TOPIC = "plant/line1/sim-net"


def _publishing_cell(port: int, ua_port: int):
    def cell_file(folder, host):
        path = short_cell(folder, host)
        return edited_cell(folder, path, {"plant": {
            "mqtt": {"host": "127.0.0.1", "port": port, "topic": TOPIC, "keepalive_s": 5},
            "opcua": {"endpoint": f"opc.tcp://127.0.0.1:{ua_port}/cellcal/"}}}, name="sim-net-plant.yaml")
    return cell_file


def _last_result(endpoint: str) -> dict:
    """What a plant's OPC UA client reads of the cell, found by browse names."""
    from asyncua import Client

    async def read():
        async with Client(endpoint) as client:
            ns = await client.get_namespace_index("urn:cellcal:plant")
            cell = await client.nodes.objects.get_child(f"{ns}:Cell")
            last = await cell.get_child(f"{ns}:LastResult")
            out = {}
            for parent, names in ((cell, ("State", "CellName")), (last, ("RunId", "Evaluation", "WrittenBack"))):
                for name in names:
                    out[name] = (await (await parent.get_child(f"{ns}:{name}")).read_data_value()).Value.Value
            return out

    return asyncio.run(read())


def test_the_daemon_publishes_every_finished_run_and_its_state_through_a_broker_that_goes_away(tmp_path):
    broker = Broker(tmp_path / "broker").start()
    consumer = Subscriber(broker.port, TOPIC)
    ua_port = free_port()
    net = Net(tmp_path, cell_file=_publishing_cell(broker.port, ua_port), time_scale=SUITE_TIME_SCALE)
    daemon = None
    try:
        daemon = Daemon(net, tmp_path)
        one_run(net, "complete")
        consumer.wait(lambda: len(consumer.runs()) >= 1, timeout_s=30.0)
        broker.stop()  # the plant's network away: the next runs wait in the outbox
        one_run(net, "refused")
        one_run(net, "aborted")
        broker.start()
        consumer.wait(lambda: {r["id"] for r in consumer.runs()} >= {1, 2, 3}, timeout_s=60.0)
        first = {r["id"]: r for r in consumer.unique_runs()}  # repeats of (topic, run id) dropped
        runs = [first[i] for i in (1, 2, 3)]
        # each what `cellcal runs show` reads from the store for it: one store, one serializer
        for r in runs:
            shown = daemon.cli("runs", "show", str(r["id"]))
            assert (r["state"], r["result_code"]) == (shown["state"], shown["result_code"]), (r, shown)
        # the harness' short tcp-laser reaches its solve and fails its gates (too few poses), the next is refused
        # (a selector no routine has), the last aborted: none wrote a frame
        assert [r["state"] for r in runs] == ["fault", "refused", "aborted"], [(r["state"], r["reason"]) for r in runs]
        assert not any(r["written_back"] for r in runs)
        assert all(r["robot"] == net.cell.robot and r["started_by"] == "panel" for r in runs)
        # the state: online, and idle after the last run (the retained copy is the newest)
        consumer.wait(lambda: consumer.states() and consumer.states()[-1]["state"] == "idle", timeout_s=20.0)
        assert consumer.states()[-1]["online"] is True
        assert consumer.states()[-1]["outbox"] == {"pending": 0, "sent": 3, "dropped": 0}
        # the same cell over OPC UA: its state and its last result (run 3, aborted: NOK, nothing written)
        deadline = time.monotonic() + 10.0
        while (seen := _last_result(f"opc.tcp://127.0.0.1:{ua_port}/cellcal/"))["RunId"] != 3:
            assert time.monotonic() < deadline, seen
            time.sleep(0.2)
        assert seen == {"State": "idle", "CellName": net.cell.name, "RunId": 3, "Evaluation": "NOK",
                        "WrittenBack": False}, seen
        assert daemon.stop() == 0
        daemon = None
        # a clean stop says offline itself (retained)
        consumer.wait(lambda: consumer.states()[-1]["online"] is False, timeout_s=20.0)
    finally:
        if daemon is not None:
            daemon.stop()
        net.close()
        consumer.close()
        broker.stop()
