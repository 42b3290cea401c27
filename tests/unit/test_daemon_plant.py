"""How ``cellcal daemon`` starts the plant's parts (cli/daemon.py ``_publish_to_plant``): none without the
section; an OPC UA port already taken costs the OPC UA server only, with one log line, and the service runs
on (as with the status page)."""
from __future__ import annotations

import logging
import socket
from types import SimpleNamespace

from cellcal.cli.daemon import _publish_to_plant
from cellcal.config.cells import OpcuaSpec, PlantSpec


def _cell(plant):
    return SimpleNamespace(plant=plant, name="cell7", path="cell7.yaml", robot="ur10e")


def test_no_section_no_parts(tmp_path):
    assert _publish_to_plant(_cell(PlantSpec()), SimpleNamespace(status=dict), tmp_path) == []


def test_a_taken_opcua_port_costs_the_opcua_server_only(tmp_path, caplog):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        spec = PlantSpec(opcua=OpcuaSpec(endpoint=f"opc.tcp://127.0.0.1:{port}/cellcal/"))
        with caplog.at_level(logging.INFO):
            parts = _publish_to_plant(_cell(spec), SimpleNamespace(status=dict), tmp_path)
    assert parts == []
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and str(port) in errors[0] and "runs on without it" in errors[0], errors


def test_the_services_own_status_reads_as_the_cells_opcua_values():
    # what plant_feed hands the OPC UA server is Service.status() as it is: health {"level"}, the mounted tool
    # {"id", ...}, the run under way as run_id
    from cellcal.daemon.plant_values import state_values

    values, devices = state_values({"state": "running", "health": {"level": "running", "says": "tcp-laser"},
                                    "mounted_tool": {"id": 2, "name": "torch"}, "run_id": 7,
                                    "devices": {"robot": "ready", "panel": "ok"}})
    assert values == {"State": "running", "Health": "running", "MountedTool": 2, "RunUnderWay": 7}
    assert devices == {"robot": "ready", "panel": "ok"}


def test_a_tls_file_that_is_no_certificate_costs_the_mqtt_sender_only(tmp_path, caplog):
    from cellcal.config.cells import MqttSpec

    ca = tmp_path / "ca.pem"
    ca.write_text("not a certificate\n")
    spec = PlantSpec(mqtt=MqttSpec(host="127.0.0.1", topic="plant/cell7", client_id="cell7", tls_ca=str(ca)))
    with caplog.at_level(logging.INFO):
        parts = _publish_to_plant(_cell(spec), SimpleNamespace(status=dict), tmp_path)
    assert parts == []
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and "not publishing" in errors[0] and "runs on without it" in errors[0], errors
