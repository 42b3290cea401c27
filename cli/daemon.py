"""``cellcal daemon``: the service.

``cellcal daemon --cell CELL.yaml`` connects the cell's devices, checks them, tells
systemd it is ready, then serves the operator panel until SIGTERM or SIGINT: a start
request runs the selected routine (:mod:`cellcal.daemon.service`). After any crash it comes up idle:
a run found open in the store is recorded as interrupted, and nothing moves by itself.
"""
from __future__ import annotations

import logging
import signal
import sys
import threading
from contextlib import ExitStack
from dataclasses import asdict

from cellcal.cli.common import STATE_HELP, number, open_store, service_state_folder
from cellcal.daemon.claims import held
from cellcal.daemon.cells import load_cell, open_drivers
from cellcal.daemon.notify import Notifier
from cellcal.daemon.result_codes import ResultCode
from cellcal.daemon.service import Service
from cellcal.drivers.interfaces import DeviceError
from cellcal.reports.run import write_run_report
from cellcal.reports.trend import write_trend_page
from cellcal.routines.framework import registry

log = logging.getLogger("cellcal.daemon")
STOP_WAIT_S = 1.5  # how long a stop waits for the running routine to halt before leaving


def cmd_daemon(args) -> int:
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="cellcal: %(message)s", force=True)
    cell = load_cell(args.cell)
    folder = service_state_folder(args)  # made if missing; it and the store's files writable by this user
    # one service per store, per panel and per robot, held for the service's life and taken before the
    # store is touched (a second daemon must not mark the first one's live run interrupted)
    claims = ExitStack()
    claims.enter_context(held(cell, state_folder=folder, kinds=("robot", "panel")))
    try:
        store = open_store(args, create=True)
    except BaseException:
        claims.close()
        raise
    notifier = Notifier()
    stopping = threading.Event()
    # set from a thread of its own: the handler runs in the main thread, which may hold the Event's
    # lock at that moment (inside stopping.wait), and setting it there would deadlock
    previous = {sig: signal.signal(sig, lambda *_: threading.Thread(target=stopping.set).start())
                for sig in (signal.SIGTERM, signal.SIGINT)}
    if cell.plant.mqtt is not None:  # finished runs queued for the broker with their end (Store.finish_run)
        store.outbox_limit = cell.plant.mqtt.outbox_limit
    try:
        interrupted = store.mark_interrupted(int(ResultCode.INTERRUPTED))
        for run_id in interrupted:
            log.warning("run %d: interrupted (the daemon stopped during it); nothing was written back", run_id)
        store.event("start", cell.path)
        try:
            drivers = open_drivers(cell)
        except DeviceError as exc:
            log.error("cannot connect the cell's devices: %s", exc)
            store.event("fault", str(exc))
            return 1
        with drivers:
            try:
                state = drivers.robot.state()
            except DeviceError as exc:
                log.error("the robot does not answer: %s", exc)
                return 1
            service = Service(cell, drivers, store, out_dir=folder / "datasets", notifier=notifier,
                              report=lambda run_id, result, st, ending: write_run_report(
                                  folder / "reports", run_id, result, tool_id=st.run(run_id).tool_id,
                                  ending=ending),
                              reconnect=lambda: open_drivers(cell),
                              trend=lambda tool_id, trend: write_trend_page(folder / "reports" / f"tool-{tool_id}",
                                                                            trend))
            service.seen["robot"] = state.value  # as read at the start: the status page's first look
            service.panel.call("set_lamps", busy=False)
            service.discard_requests("pending when the service started")
            service.announce_interrupted(interrupted)
            service.resume_owed_frame()
            service.announce_tool_blocks()
            page = _serve_status_page(cell, service, folder)
            plant = _publish_to_plant(cell, service, folder)
            log.info("ready: cell %s, robot %s; the panel offers %s", cell.name, state.value,
                     ", ".join(f"{k} {v}" for k, v in service.routines.items()
                               if registry.unavailable(v, cell) is None))
            notifier.ready(f"idle; robot {state.value}")
            try:
                while not stopping.is_set():
                    service.poll_panel()
                    notifier.watchdog()
                    stopping.wait(args.poll_s)
                notifier.stopping()
                log.info("stopping")
                if service.busy():
                    service.request_abort("the service is stopping")
                service.wait(STOP_WAIT_S)  # the run's end, and its last words to the panel and the store
                store.event("stop", None)
            finally:
                for part in plant:
                    part.stop()
                if page is not None:
                    page.stop()
                if service.drivers is not drivers:  # reconnected after a lost robot
                    service.drivers.close()
        return 0
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        notifier.close()
        store.close()
        claims.close()


def _serve_status_page(cell, service: Service, folder):
    """The read-only status page and JSON API (the cell file's ``status_page``), in a thread of
    its own; None when turned off or when its address cannot be had (the service runs on: the
    panel is what runs the cell, the page only shows it)."""
    spec = cell.status_page
    if not spec.enabled:
        log.info("status page: off (status_page.enabled is false)")
        return None
    from cellcal.daemon.status_http import exposure_warning  # only a daemon serving it needs these
    from cellcal.daemon.status_server import StatusServer

    server = StatusServer(status=service.status, state_dir=folder, spec=spec,
                          tool_names={tool_id: tool.name for tool_id, tool in (cell.tools or {}).items()},
                          tool_bands={tool_id: asdict(tool.bands) for tool_id, tool in (cell.tools or {}).items()})
    try:
        server.start()
    except OSError as exc:
        log.error("status page not served: %s (status_page in %s: another port, or enabled: false); the service "
                  "runs on without it", exc, cell.path)
        return None
    log.info("status page and JSON API (read-only): %s", server.url)
    beyond = exposure_warning(spec.host, spec.port)
    if beyond is not None:
        log.warning("%s: anyone on that network can read it (read-only; status_page.host in %s)", beyond, cell.path)
    return server


def _publish_to_plant(cell, service: Service, folder) -> list:
    """The publishers of the cell file's ``plant`` section, started (none when it has none): the MQTT sender
    (finished runs from the store's outbox, the state retained) and the read-only OPC UA server with its feed;
    each part that cannot start is said once and left out, and the service runs on (the panel runs the cell,
    the plant only watches it)."""
    parts = []
    spec = cell.plant.mqtt
    if spec is not None:
        from cellcal.daemon.plant_mqtt import MqttPublisher  # only a daemon publishing needs paho

        try:
            parts.append(MqttPublisher(spec, folder, cell.name, status=service.status, robot=cell.robot).start())
        except (OSError, ValueError) as exc:  # a TLS file that is no certificate (ssl.SSLError is an OSError)
            log.error("plant: not publishing to the MQTT broker %s:%d: %s (plant.mqtt in %s); the service runs on "
                      "without it", spec.host, spec.port, exc, cell.path)
        else:
            log.info("plant: publishing to the MQTT broker %s:%d under %s", spec.host, spec.port, spec.topic)
    ua = cell.plant.opcua
    if ua is not None:
        from cellcal.daemon.plant_feed import OpcuaFeed  # only a daemon serving OPC UA needs asyncua
        from cellcal.daemon.plant_opcua import OpcuaServer, PlantError

        server = OpcuaServer(ua.endpoint, cell.name, security=ua.security, certificate=ua.certificate,
                             private_key=ua.private_key)
        try:
            server.start()
        except PlantError as exc:
            log.error("%s (plant.opcua in %s: another port, or leave it out); the service runs on without it",
                      exc, cell.path)
        else:
            parts.append(OpcuaFeed(server, folder, service.status).start())
            log.info("plant: OPC UA server (read-only) on %s, security %s", ua.endpoint, ua.security)
    return parts


def add_parser(sub) -> None:
    p = sub.add_parser("daemon", help="the service: run routines from the operator panel, write back tool frames",
                       description="Connect the cell's devices, tell systemd it is ready (Type=notify), and serve "
                                   "the operator panel until SIGTERM/SIGINT: a start request runs the selected "
                                   "routine; a tool frame is written back only when every gate passes.")
    p.add_argument("--cell", required=True, metavar="CELL.yaml", help="cell file, or a shipped cell's name")
    p.add_argument("--state-dir", metavar="DIR", help=STATE_HELP)
    p.add_argument("--poll-s", type=number(0.005, 10.0, unit="s"), default=0.05,
                   help="panel polling interval, 0.005 .. 10 s (default 0.05 s)")
    p.set_defaults(func=cmd_daemon)
