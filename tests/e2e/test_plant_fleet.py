"""A fleet on one broker: twenty simulated cells in process, each its own service, store and publisher (as
``cellcal daemon`` wires them: cli/daemon.py ``_publish_to_plant``), publishing to one real Mosquitto that is
stopped while the cells run on and started again. Every run of every cell arrives, once after dropping repeats
of (topic, run id), in each cell's order; ``cellcal plant`` then shows all twenty."""
from __future__ import annotations

import json

import pytest

from cellcal.cli.daemon import _publish_to_plant
from cellcal.daemon.cells import load_cell, open_drivers
from cellcal.daemon.service import Service
from cellcal.daemon.store import Store
from support.cell_edits import edited_cell
from support.cli_run import run_cli
from support.mosquitto import Broker, Subscriber
from support.service_panel import press

CELLS = 20


@pytest.mark.slow
def test_twenty_cells_on_one_broker_lose_nothing_while_it_restarts(tmp_path, capsys):
    broker = Broker(tmp_path / "broker").start()
    consumer = Subscriber(broker.port, "plant")  # a plant consumer with a persistent session, there from the start
    cells = []
    try:
        for k in range(CELLS):
            folder = tmp_path / f"cell{k:02d}"
            folder.mkdir()
            cell = load_cell(edited_cell(folder, "sim", {
                "cell": {"name": f"cell{k:02d}"},
                "plant": {"mqtt": {"host": "127.0.0.1", "port": broker.port, "topic": f"plant/line1/cell{k:02d}"}}}))
            store = Store.open(folder / "state")
            store.outbox_limit = cell.plant.mqtt.outbox_limit  # as cmd_daemon sets it before any run ends
            drivers = open_drivers(cell).__enter__()
            service = Service(cell, drivers, store, out_dir=folder / "state" / "datasets")
            cells.append((cell, store, drivers, service, _publish_to_plant(cell, service, folder / "state")))
        for k, (cell, store, drivers, service, _) in enumerate(cells):
            # every fourth cell calibrates (a result with its frame), the others' starts are refused (a selector no
            # routine has): both are finished runs the plant must get (a calibration costs 0.8 s in process)
            assert (press(service, drivers.panel, "tcp-npoint").code == 0) if k % 4 == 0 else \
                (press(service, drivers.panel, 97).code != 0)
        broker.stop()  # the broker away while every cell runs on: two starts refused (a selector no routine has)
        for cell, store, drivers, service, _ in cells:
            assert press(service, drivers.panel, 99).code != 0
            assert press(service, drivers.panel, 98).code != 0
        broker.start()
        # what each cell's own store says finished: the plant must get exactly these, in this order
        expected = {f"plant/line1/{cell.name}": [r.id for r in reversed(store.runs(10))]
                    for cell, store, *_ in cells}
        assert all(ids == [1, 2, 3] for ids in expected.values())
        consumer.wait(lambda: len({(r["topic"], r["id"]) for r in consumer.runs()}) >= 3 * CELLS, timeout_s=60.0)
        got: dict[str, list[int]] = {}
        first = {(r["topic"], r["id"]): r for r in consumer.unique_runs()}
        for topic, run_id in first:
            got.setdefault(topic, []).append(run_id)
        assert got == expected
        for _, store, *_ in cells:
            consumer.wait(lambda: store.outbox_counts()["pending"] == 0)
            assert store.outbox_counts() == {"pending": 0, "sent": 3, "dropped": 0}
        code, out, err = run_cli(capsys, "plant", "--mqtt", f"127.0.0.1:{broker.port}", "--json", "--for", "1")
        assert code == 0, err
        shown = json.loads(out)["cells"]
        assert [c["topic"] for c in shown] == sorted(expected)
        assert all(c["online"] and c["last_run"]["id"] == 3 and c["last_run"]["state"] == "refused" for c in shown)
        calibrated = [c for k, c in enumerate(shown) if k % 4 == 0]
        assert all(first[(c["topic"], 1)]["result"]["tool_frame"]["z_mm"] > 0 for c in calibrated)
    finally:
        consumer.close()
        for cell, store, drivers, service, parts in cells:
            for part in parts:
                part.stop()
            drivers.__exit__(None, None, None)
            store.close()
        broker.stop()
