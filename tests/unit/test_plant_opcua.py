"""The plant's OPC UA server (daemon/plant_opcua.py) as a plant's client sees it, through
asyncua's own client on loopback: the nodes found by browse names, the values after the
service's updates, the ResultReady event, no write getting through, one clear error for an
address or a certificate that cannot be served, and encryption with a certificate."""
from __future__ import annotations

import asyncio
import datetime
import ipaddress
import logging
import math
import socket
import threading
import time

import pytest
from asyncua import Client, ua
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import rsa
from cryptography.x509.oid import NameOID

from cellcal.daemon.plant_opcua import NAMESPACE_URI, OpcuaServer, PlantError
from cellcal.daemon.plant_values import evaluation
from support import loopback

WAIT_S = 5.0  # the longest a value or an event may take to reach a client on loopback
CELL_VARIABLES = ("CellName", "State", "Health", "MountedTool", "RunUnderWay")
RESULT_VARIABLES = ("RunId", "Routine", "ToolId", "Verdict", "Evaluation", "ResultCode", "ResultName", "X_mm",
                    "Y_mm", "Z_mm", "Rx_deg", "Ry_deg", "Rz_deg", "PassedGates", "WrittenBack", "FinishedAt")
EVENT_FIELDS = ("RunId", "Routine", "ToolId", "Verdict", "Evaluation", "ResultCode", "WrittenBack")

FINISHED_AT = 1_780_000_000.25
CALIBRATION = {"id": 42, "routine": "tcp-laser", "cell": "cell-7", "tool_id": 3, "started_at": FINISHED_AT - 90.0,
               "finished_at": FINISHED_AT, "state": "done", "result_code": 0, "result_name": "OK", "reason": None,
               "verdict": None, "passed_gates": True, "written_back": True, "report_url": None,
               "result": {"tool_frame": {"x_mm": 1.25, "y_mm": -2.5, "z_mm": 151.75, "rx_deg": 0.5,
                                         "ry_deg": -0.25, "rz_deg": 90.0, "pose_m_rad": [0.0] * 6}}}
ALARM = {"id": 43, "routine": "tcp-check", "tool_id": 3, "verdict": "alarm", "result_code": 33,
         "result_name": "CHECK_ALARM", "passed_gates": False, "written_back": False, "finished_at": FINISHED_AT + 60,
         "state": "done", "result": {"change": {"tip_mm": 2.1}}}


def free_port(host: str) -> int:
    with socket.socket() as probe:
        probe.bind((host, 0))
        return probe.getsockname()[1]


def plant_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "cellcal-plant-opcua"]


async def until(read, want, what: str):
    """Poll `read()` until it equals `want` (NaN equal to NaN), for at most WAIT_S."""
    deadline = time.monotonic() + WAIT_S
    while True:
        got = await read()
        if got == want or (isinstance(got, float) and isinstance(want, float) and math.isnan(got) and math.isnan(want)):
            return
        if time.monotonic() > deadline:
            pytest.fail(f"{what}: {got!r} after {WAIT_S} s, expected {want!r}")
        await asyncio.sleep(0.02)


async def cell_nodes(client: Client):
    """Objects -> Cell and Cell -> LastResult, by browse names as a plant's client finds them."""
    ns = await client.get_namespace_index(NAMESPACE_URI)
    cell = await client.nodes.objects.get_child(f"{ns}:Cell")
    return ns, cell, await cell.get_child(f"{ns}:LastResult")


async def value(parent, ns: int, name: str):
    return (await (await parent.get_child(f"{ns}:{name}")).read_data_value()).Value.Value


@pytest.fixture(scope="module")
def served():
    """One server on a loopback address of the module's own: (server, endpoint)."""
    with loopback.held() as host:
        endpoint = f"opc.tcp://{host}:{free_port(host)}"
        server = OpcuaServer(endpoint, "cell-7")
        server.start()
        try:
            yield server, endpoint
        finally:
            server.stop()


# -- what a plant's client finds and reads ------------------------------------------------------------


def test_a_plant_client_finds_the_cell_and_its_last_result_by_browse_names_and_no_methods(served):
    _, endpoint = served

    async def browse():
        async with Client(endpoint) as client:
            ns, cell, last = await cell_nodes(client)
            names = {(await n.read_browse_name()).Name: await n.read_node_class() for n in await cell.get_children()}
            assert names == {**dict.fromkeys(CELL_VARIABLES, ua.NodeClass.Variable),
                             "Devices": ua.NodeClass.Object, "LastResult": ua.NodeClass.Object}
            assert [(await n.read_browse_name()).Name for n in await last.get_children()] == list(RESULT_VARIABLES)
            assert await value(cell, ns, "CellName") == "cell-7"
            assert await value(last, ns, "Evaluation") == ""  # no result yet
            assert await cell.read_event_notifier() == {ua.EventNotifier.SubscribeToEvents}
            assert not await cell.get_methods() and not await last.get_methods()
            event_type = await client.nodes.base_event_type.get_child(f"{ns}:ResultReadyEventType")
            assert {(await p.read_browse_name()).Name for p in await event_type.get_properties()} == set(EVENT_FIELDS)

    asyncio.run(browse())


def test_the_cells_state_reads_as_the_service_last_updated_it(served):
    server, endpoint = served

    async def read_state():
        async with Client(endpoint) as client:
            ns, cell, _ = await cell_nodes(client)
            server.update_state({"state": "running", "health": "running", "mounted_tool": 3, "run": 42,
                                 "devices": {"robot": "ready", "panel": "ok"}})
            await until(lambda: value(cell, ns, "RunUnderWay"), 42, "RunUnderWay")
            assert [await value(cell, ns, n) for n in ("State", "Health", "MountedTool")] == ["running", "running", 3]
            devices = await cell.get_child(f"{ns}:Devices")
            assert [await value(devices, ns, n) for n in ("panel", "robot")] == ["ok", "ready"]
            # the service's own status shapes, a run no longer under way, a device gone: nulls
            server.update_state({"state": "idle", "health": {"level": "ok", "says": "idle"},
                                 "mounted_tool": {"id": 4, "name": "gripper"}, "run": None,
                                 "devices": {"robot": "ready"}})
            await until(lambda: value(cell, ns, "State"), "idle", "State")
            assert [await value(cell, ns, n) for n in ("Health", "MountedTool", "RunUnderWay")] == ["ok", 4, None]
            assert await value(devices, ns, "panel") is None

    asyncio.run(read_state())


def test_a_published_result_reads_back_and_fires_result_ready_with_its_fields(served):
    server, endpoint = served

    class Events:
        def __init__(self):
            self.queue = asyncio.Queue()

        def event_notification(self, event):
            self.queue.put_nowait(event)

    async def publish():
        async with Client(endpoint) as client:
            ns, cell, last = await cell_nodes(client)
            event_type = await client.nodes.base_event_type.get_child(f"{ns}:ResultReadyEventType")
            events = Events()
            subscription = await client.create_subscription(20, events)
            await subscription.subscribe_events(cell, event_type)
            server.publish_result(CALIBRATION)
            event = await asyncio.wait_for(events.queue.get(), WAIT_S)
            assert {f: getattr(event, f) for f in EVENT_FIELDS} == {
                "RunId": 42, "Routine": "tcp-laser", "ToolId": 3, "Verdict": None, "Evaluation": "OK",
                "ResultCode": 0, "WrittenBack": True}
            assert event.SourceName == "Cell"
            assert abs(event.Time.timestamp() - FINISHED_AT) < 1e-3
            values = {n: await value(last, ns, n) for n in RESULT_VARIABLES}
            finished = values.pop("FinishedAt")
            assert abs(finished.replace(tzinfo=datetime.timezone.utc).timestamp() - FINISHED_AT) < 1e-3
            assert values == {"RunId": 42, "Routine": "tcp-laser", "ToolId": 3, "Verdict": None, "Evaluation": "OK",
                              "ResultCode": 0, "ResultName": "OK", "X_mm": 1.25, "Y_mm": -2.5, "Z_mm": 151.75,
                              "Rx_deg": 0.5, "Ry_deg": -0.25, "Rz_deg": 90.0, "PassedGates": True,
                              "WrittenBack": True}
            # a check's alarm: NOK, no tool frame in its result, so no coordinates
            server.publish_result(ALARM)
            event = await asyncio.wait_for(events.queue.get(), WAIT_S)
            assert (event.RunId, event.Verdict, event.Evaluation, event.ResultCode) == (43, "alarm", "NOK", 33)
            assert await value(last, ns, "ResultName") == "CHECK_ALARM"
            assert math.isnan(await value(last, ns, "X_mm"))
            await subscription.delete()

    asyncio.run(publish())


def test_a_result_missing_its_keys_reads_null_and_nan_and_never_raises(served):
    server, endpoint = served

    async def publish():
        async with Client(endpoint) as client:
            ns, _, last = await cell_nodes(client)
            server.publish_result(None)  # not even a dict: nothing raises
            server.publish_result({"id": 44, "tool_id": "three", "result_code": 1.5, "finished_at": "later",
                                   "result": {"tool_frame": {"x_mm": "1", "y_mm": None}}})
            server.update_state({"devices": ["not", "a", "dict"], "mounted_tool": True})
            await until(lambda: value(last, ns, "RunId"), 44, "RunId")
            values = {n: await value(last, ns, n) for n in RESULT_VARIABLES}
            assert all(math.isnan(values.pop(n)) for n in ("X_mm", "Y_mm", "Z_mm", "Rx_deg", "Ry_deg", "Rz_deg"))
            assert values == {"RunId": 44, "Evaluation": "NOK",
                              **{n: None for n in ("Routine", "ToolId", "Verdict", "ResultCode", "ResultName",
                                                   "PassedGates", "WrittenBack", "FinishedAt")}}

    asyncio.run(publish())


@pytest.mark.parametrize("run, said", [
    ({"verdict": "ok", "result_code": 0}, "OK"),
    ({"verdict": "corrected", "result_code": 0, "passed_gates": True}, "OK"),
    ({"verdict": "alarm", "result_code": 33}, "NOK"),
    ({"verdict": "drift", "result_code": 34}, "NOK"),
    ({"verdict": None, "passed_gates": True, "result_code": 0}, "OK"),  # a calibration that passed
    ({"verdict": None, "passed_gates": True, "result_code": 32}, "NOK"),  # passed, but the write-back failed
    ({"verdict": None, "passed_gates": False, "result_code": 31}, "NOK"),
    ({"state": "fault", "result_code": 21}, "NOK"),  # no result reached
    ({}, "NOK"),
])
def test_the_evaluation_is_ok_for_a_good_check_or_a_calibration_that_passed_and_nok_otherwise(run, said):
    assert evaluation(run) == said


def test_no_variable_takes_a_write_and_the_admin_login_is_refused(served):
    _, endpoint = served

    async def write_all(client: Client) -> int:
        ns, cell, last = await cell_nodes(client)
        devices = await cell.get_child(f"{ns}:Devices")
        refused = 0
        for node in [*await cell.get_variables(), *await last.get_variables(), *await devices.get_variables()]:
            level = await node.read_attribute(ua.AttributeIds.UserAccessLevel)
            assert level.Value.Value == ua.AccessLevel.CurrentRead.mask
            name = (await node.read_browse_name()).Name
            data = await node.read_data_value()
            try:
                await node.write_value(ua.DataValue(data.Value))
            except ua.UaStatusCodeError as exc:
                assert exc.code in (ua.StatusCodes.BadUserAccessDenied, ua.StatusCodes.BadNotWritable), name
                refused += 1
            else:
                pytest.fail(f"{name} took a client's write")
            with pytest.raises(ua.UaStatusCodeError):
                await node.write_attribute(ua.AttributeIds.DisplayName, ua.DataValue(ua.LocalizedText("x")))
        return refused

    async def as_plant():
        async with Client(endpoint) as client:
            assert await write_all(client) >= len(CELL_VARIABLES) + len(RESULT_VARIABLES)
        # asyncua makes a login as "admin" its administrator, unless told not to: here no login by
        # name is on offer at all
        admin = Client(endpoint)
        admin.set_user("admin")
        admin.set_password("any")
        with pytest.raises(ua.UaStatusCodeError) as refused:
            await admin.connect()
        assert refused.value.code == ua.StatusCodes.BadIdentityTokenRejected

    asyncio.run(as_plant())


# -- what cannot be served --------------------------------------------------------------------------------


def test_a_second_server_on_the_same_port_is_one_error_and_the_first_serves_on(served):
    first, endpoint = served
    before = len(plant_threads())
    t0 = time.monotonic()
    with pytest.raises(PlantError) as caught:
        OpcuaServer(endpoint, "cell-8").start()
    assert time.monotonic() - t0 < 2.0
    assert str(caught.value) == f"OPC UA server: cannot listen on {endpoint}: the port is taken (another program " \
                                "listens on it)"
    assert len(plant_threads()) == before

    async def still_there():
        async with Client(endpoint) as client:
            ns, cell, _ = await cell_nodes(client)
            assert await value(cell, ns, "CellName") == "cell-7"

    asyncio.run(still_there())


@pytest.mark.parametrize("endpoint, said", [
    ("http://127.0.0.1:4840", "an endpoint is opc.tcp://HOST:PORT"),
    ("opc.tcp://127.0.0.1", "the endpoint names no port"),
    ("opc.tcp://127.0.0.1:99999", "the port is not a number from 1 to 65535"),
    ("opc.tcp://no-such-host.invalid:4840", "no such host"),
])
def test_an_endpoint_that_cannot_be_served_is_one_error_naming_it(endpoint, said):
    before = len(plant_threads())
    with pytest.raises(PlantError, match=f"^OPC UA server: cannot listen on {endpoint}: {said}"):
        OpcuaServer(endpoint, "cell-7").start()
    assert len(plant_threads()) == before


def test_a_missing_certificate_file_is_one_error_naming_the_file(tmp_path, loopback_host):
    key = tmp_path / "key.pem"
    key.write_bytes(b"")
    missing = tmp_path / "no-such-cert.der"
    server = OpcuaServer(f"opc.tcp://{loopback_host}:{free_port(loopback_host)}", "cell-7",
                         security="Basic256Sha256_SignAndEncrypt", certificate=str(missing), private_key=str(key))
    with pytest.raises(PlantError, match=f"cannot read the certificate {missing}: No such file"):
        server.start()
    server.stop()  # nothing to stop: a no-op
    with pytest.raises(PlantError, match="unknown security 'Basic128'"):
        OpcuaServer(f"opc.tcp://{loopback_host}:4840", "cell-7", security="Basic128").start()


# -- security ---------------------------------------------------------------------------------------------


def self_signed(folder, name: str, uri: str, host: str, der: bool):
    """A certificate and its key, as `folder`/name.der (or .pem) and `folder`/name-key.pem."""
    key = rsa.generate_private_key(public_exponent=65537, key_size=2048)
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)])
    now = datetime.datetime.now(datetime.timezone.utc)
    cert = (x509.CertificateBuilder().subject_name(subject).issuer_name(subject).public_key(key.public_key())
            .serial_number(x509.random_serial_number()).not_valid_before(now - datetime.timedelta(days=1))
            .not_valid_after(now + datetime.timedelta(days=30))
            .add_extension(x509.SubjectAlternativeName([x509.UniformResourceIdentifier(uri), x509.DNSName("localhost"),
                                                        x509.IPAddress(ipaddress.ip_address(host))]), critical=False)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, content_commitment=True, key_encipherment=True,
                                         data_encipherment=True, key_agreement=False, key_cert_sign=False,
                                         crl_sign=False, encipher_only=False, decipher_only=False), critical=True)
            .sign(key, hashes.SHA256()))
    cert_path = folder / (f"{name}.der" if der else f"{name}.pem")
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.DER if der else serialization.Encoding.PEM))
    key_path = folder / f"{name}-key.pem"
    key_path.write_bytes(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.TraditionalOpenSSL,
                                           serialization.NoEncryption()))
    return cert_path, key_path


def test_sign_and_encrypt_serves_a_client_of_that_policy_and_no_other(tmp_path, loopback_host, monkeypatch):
    server_cert, server_key = self_signed(tmp_path, "server", "urn:cellcal:test:server", loopback_host, der=True)
    client_cert, client_key = self_signed(tmp_path, "client", "urn:cellcal:test:client", loopback_host, der=False)
    endpoint = f"opc.tcp://{loopback_host}:{free_port(loopback_host)}"
    server = OpcuaServer(endpoint, "cell-7", security="Basic256Sha256_SignAndEncrypt", certificate=str(server_cert),
                         private_key=str(server_key))
    server.start()

    async def connect():
        client = Client(endpoint)
        client.application_uri = "urn:cellcal:test:client"
        await client.set_security(SecurityPolicyBasic256Sha256, str(client_cert), str(client_key),
                                  server_certificate=str(server_cert))
        async with client:
            ns, cell, _ = await cell_nodes(client)
            assert await value(cell, ns, "CellName") == "cell-7"
        endpoints = await Client(endpoint).connect_and_get_server_endpoints()  # on offer: this one only
        assert {(e.SecurityPolicyUri, e.SecurityMode) for e in endpoints} == {
            (SecurityPolicyBasic256Sha256.URI, ua.MessageSecurityMode.SignAndEncrypt)}
        # a client that ignores the offer and asks for a session in the clear is refused
        monkeypatch.setattr(Client, "find_endpoint", staticmethod(lambda found, mode, uri: found[0]))
        with pytest.raises(ua.UaStatusCodeError) as refused:
            async with Client(endpoint, timeout=2) as plain:
                await plain.nodes.objects.get_children()
        assert refused.value.code == ua.StatusCodes.BadUserAccessDenied

    try:
        asyncio.run(connect())
    finally:
        server.stop()


def test_no_security_beyond_loopback_is_served_with_a_warning(caplog):
    caplog.set_level(logging.WARNING, logger="cellcal.plant")
    endpoint = f"opc.tcp://0.0.0.0:{free_port('0.0.0.0')}"
    server = OpcuaServer(endpoint, "cell-7")
    server.update_state({"state": "idle"})  # before start: served from the start
    server.start()
    try:
        warned = [r for r in caplog.records if r.name == "cellcal.plant" and r.levelno == logging.WARNING]
        assert len(warned) == 1 and "anyone on the network" in warned[0].getMessage()

        async def read():
            async with Client(endpoint.replace("0.0.0.0", "127.0.0.1")) as client:
                ns, cell, _ = await cell_nodes(client)
                assert await value(cell, ns, "State") == "idle"

        asyncio.run(read())
    finally:
        before = len(plant_threads())
        server.stop()
        server.stop()  # again: a no-op
    assert len(plant_threads()) == before - 1
