"""``cellcal plant``: the cells publishing to one MQTT broker, as a plant engineer watches them (docs/plant.md).

A subscriber only: it connects to the broker, subscribes to ``--topic`` (``plant/#``: every cell under
``plant/``), and keeps, per cell topic, the newest retained state and the last finished run. Without
``--json`` it prints the table whenever it changes, until Ctrl-C; with ``--json --for SECONDS`` it listens
that long (the retained states arrive at once) and prints one JSON object, for scripts.
"""
from __future__ import annotations

import json
import sys
import threading
import time

from cellcal.cli.common import UsageError, number


def _host_port(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep:
        return text, 1883
    if not host or not port.isdigit() or not 1 <= int(port) <= 65535:
        raise UsageError(f"--mqtt {text}: expected HOST or HOST:PORT (port 1..65535)")
    return host, int(port)


def cell_of(topic: str) -> tuple[str, str] | None:
    """(cell topic, kind) of a message's topic: ``T/state`` -> (T, "state"), ``T/runs/<id>`` -> (T, "run")."""
    if topic.endswith("/state"):
        return topic[: -len("/state")], "state"
    head, sep, tail = topic.rpartition("/runs/")
    if sep and tail.isdigit():
        return head, "run"
    return None


def _run_id(doc: dict) -> int:
    value = doc.get("id")
    return value if isinstance(value, int) else -1


class Fleet:
    """What the broker told about each cell: its newest state and its last finished run (by run id)."""

    def __init__(self):
        self.lock = threading.Lock()
        self.cells: dict[str, dict] = {}
        self.changed = threading.Event()

    def take(self, topic: str, payload: bytes) -> None:
        where = cell_of(topic)
        if where is None:
            return
        try:
            doc = json.loads(payload)
        except ValueError:
            return  # not a cellcal message: another publisher under the same topic
        if not isinstance(doc, dict):
            return
        cell, kind = where
        with self.lock:
            entry = self.cells.setdefault(cell, {"state": None, "last_run": None})
            if kind == "state":
                entry["state"] = doc
            elif entry["last_run"] is None or _run_id(doc) >= _run_id(entry["last_run"]):
                entry["last_run"] = doc  # a repeat or an older run sent again never replaces a newer one
        self.changed.set()

    def snapshot(self) -> dict:
        with self.lock:
            cells = []
            for topic in sorted(self.cells):
                e = self.cells[topic]
                state, run = e["state"] or {}, e["last_run"]
                said = state.get("last_run")  # the state's own (retained: there for a late subscriber too)
                if isinstance(said, dict) and (run is None or _run_id(said) >= _run_id(run)):
                    run = said
                cells.append({"topic": topic, "cell_name": state.get("cell_name") or (run or {}).get("cell_name"),
                              "online": state.get("online"), "state": state.get("state"),
                              "health": state.get("health"), "mounted_tool": state.get("mounted_tool"),
                              "outbox": state.get("outbox"),
                              "last_run": None if run is None else {
                                  k: run.get(k) for k in ("id", "routine", "tool_id", "state", "result_code",
                                                          "result_name", "verdict", "passed_gates", "written_back",
                                                          "finished_at")}})
            return {"cells": cells}


def table(snapshot: dict) -> str:
    rows = [f"{'cell':<28} {'online':<7} {'state':<12} {'health':<10} {'tool':<5} last run"]
    for c in snapshot["cells"]:
        run = c["last_run"]
        last = "-" if run is None else (f"{run['id']} {run['routine']} {run['state']}"
                                        f"{'' if run['verdict'] is None else ' ' + str(run['verdict'])}"
                                        f"{' written' if run['written_back'] else ''}")
        online = {True: "yes", False: "NO", None: "?"}[c["online"]]
        rows.append(f"{c['topic']:<28} {online:<7} {str(c['state'] or '-'):<12} {str(c['health'] or '-'):<10} "
                    f"{str(c['mounted_tool'] if c['mounted_tool'] is not None else '-'):<5} {last}")
    return "\n".join(rows)


def cmd_plant(args) -> int:
    import paho.mqtt.client as mqtt  # only this command needs it

    host, port = _host_port(args.mqtt)
    if args.for_s is not None and not args.json:
        raise UsageError("--for: says how long --json listens; give --json as well")
    fleet = Fleet()
    problem = {}
    connected = threading.Event()

    def on_connect(client, userdata, flags, reason_code, properties=None):
        if reason_code.is_failure:
            problem["why"] = f"the broker {host}:{port} refused the connection: {reason_code}"
            connected.set()
            return
        client.subscribe(args.topic, qos=1)
        connected.set()

    client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, clean_session=True)
    if args.username is not None:
        password = None
        if args.password_file is not None:
            try:
                with open(args.password_file) as f:
                    password = f.read().rstrip("\r\n")
            except OSError as exc:
                raise UsageError(f"--password-file {args.password_file}: {exc.strerror or exc}") from None
        client.username_pw_set(args.username, password)
    client.on_connect = on_connect
    client.on_message = lambda c, u, msg: fleet.take(msg.topic, msg.payload)
    try:
        client.connect(host, port, keepalive=30)
    except OSError as exc:
        print(f"cellcal plant: cannot reach the broker {host}:{port}: {exc.strerror or exc}", file=sys.stderr)
        return 1
    client.loop_start()
    try:
        if not connected.wait(10.0) or problem:
            print(f"cellcal plant: {problem.get('why', f'no answer from the broker {host}:{port} within 10 s')}",
                  file=sys.stderr)
            return 1
        if args.json:
            time.sleep(args.for_s if args.for_s is not None else 2.0)
            print(json.dumps(fleet.snapshot()))
            return 0
        while True:  # the table whenever it changes, until Ctrl-C
            if fleet.changed.wait(1.0):
                fleet.changed.clear()
                print(table(fleet.snapshot()) + "\n", flush=True)
    except KeyboardInterrupt:
        return 0
    finally:
        client.disconnect()
        client.loop_stop()


def add_parser(sub) -> None:
    p = sub.add_parser("plant", help="the cells publishing to one MQTT broker: their state and last result",
                       description="Subscribe to a plant's MQTT broker (subscriber only: nothing is published) and "
                                   "show every cell publishing under --topic: online or not, its state, health, "
                                   "mounted tool and last finished run. The table is printed whenever it changes, "
                                   "until Ctrl-C; --json --for SECONDS prints one JSON object after listening that "
                                   "long (the retained states arrive at once).")
    p.add_argument("--mqtt", required=True, metavar="HOST[:PORT]", help="the broker (port 1883 when not given)")
    p.add_argument("--topic", default="plant/#", help="the topic filter to subscribe to (default plant/#)")
    p.add_argument("--username", help="the broker's user name, when it asks for one")
    p.add_argument("--password-file", metavar="FILE", help="with --username: a file holding the password")
    p.add_argument("--json", action="store_true", help="print one JSON object (after --for seconds, default 2)")
    p.add_argument("--for", dest="for_s", type=number(0.1, 3600.0, unit="s"), metavar="SECONDS",
                   help="with --json: how long to listen, 0.1 .. 3600 s (default 2 s)")
    p.set_defaults(func=cmd_plant)
