"""The cell's state and its last result for the plant, served read-only over OPC UA.

A plant (an MES, a line PLC, a SCADA) reads what the cell is doing and what its last run
found without knowing cellcal's JSON API: one object ``Cell`` under Objects, in the namespace
``urn:cellcal:plant``, with the variables ``CellName``, ``State``, ``Health``, ``MountedTool``,
``RunUnderWay``, a child object ``Devices`` (one text per device: robot, panel, trigger,
tracker, as the status page says them) and a child object ``LastResult``: ``RunId``,
``Routine``, ``ToolId``, ``Verdict``, ``Evaluation``, ``ResultCode``, ``ResultName``, the tool
frame found (``X_mm`` .. ``Rz_deg``: mm and a rotation vector in degrees, as the status page
shows it), ``PassedGates``, ``WrittenBack``, ``FinishedAt``. Each ``publish_result`` also fires
a ``ResultReadyEventType`` event (a subtype of BaseEventType) from ``Cell``, carrying
``RunId``, ``Routine``, ``ToolId``, ``Verdict``, ``Evaluation``, ``ResultCode`` and
``WrittenBack``, so a client learns of a new result without polling. Node ids are strings
(``ns=<urn:cellcal:plant>;s=Cell.LastResult.RunId``) and stay the same across restarts, but a
client should find the nodes by their browse names.

What is taken from OPC 40001-101 (OPC UA for Machinery, Part 101: Result Transfer): a result
is a record of its own, kept apart from the machine's live state; it carries an evaluation,
``OK`` or ``NOK`` (``Evaluation``, the same two words), beside its metadata (which run, which
routine and tool, when it finished, the result code and its name); a client is told of a new
result by an event and may then read it. What is not: the companion specification's
information model itself (``ResultManagementType``, ``ResultType``, ``ResultMetaDataType``, the
``GetLatestResult`` and ``GetResultById`` methods, partial results, result files), nor the
Machinery identification of OPC 40001-1. Only the last result is held: the results store
and the JSON API keep the history. A missing value is null (a number: NaN), never an
invented one; ``Evaluation`` is empty until a result exists, then ``OK`` when a check's
verdict is ``ok`` or ``corrected``, or, for a calibration (no verdict), when it passed every
quality gate with result code 0, and ``NOK`` otherwise.

Read-only by construction, as the status page is: every variable's access level is
CurrentRead alone, so a client's write fails (``BadUserAccessDenied``); there are no methods;
every session is an anonymous reader (the library's built-in remote administrator is turned
off, and no user name or certificate logs in as more). ``security="none"`` serves without
signing or encryption: anyone who can reach the port reads the cell, which is logged as a
warning when the endpoint is not a loopback address. ``Basic256Sha256_SignAndEncrypt`` signs
and encrypts every message with the given certificate and private key (DER or PEM, an RSA
key without a password), and refuses a session over any other channel; it does not check
the client's certificate against a trust list, since reading is all any client can do.

The server is asyncua's, on an asyncio event loop in a daemon thread of its own, because the
rest of the service is threaded. ``update_state`` and ``publish_result`` may be called from
any thread and never block on the network: they turn the dicts into values at once
(:mod:`.plant_values`, which knows no protocol) and hand them to the loop, which applies
them in order. A plant interface must never slow a run or
take the service down, so nothing here raises into the caller after ``start``; ``start``
raises :class:`PlantError` with one message for a configuration that cannot be served.
"""
from __future__ import annotations

import asyncio
import collections
import errno
import ipaddress
import logging
import socket
import threading
from dataclasses import dataclass
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path
from urllib.parse import urlsplit

from asyncua import Server, ua
from asyncua.crypto.permission_rules import User, UserRole
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import rsa

from cellcal.daemon.plant_values import (CELL_NAMES, EMPTY_RESULT, FRAME_VARIABLES, RESULT_NAMES, browse_name,
                                         result_values, state_values, text)

log = logging.getLogger("cellcal.plant")

NAMESPACE_URI = "urn:cellcal:plant"
SECURITY = {"none": ua.SecurityPolicyType.NoSecurity,
            "Basic256Sha256_SignAndEncrypt": ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt}
PENDING_LIMIT = 200  # updates waiting for the server's loop; past this the oldest are dropped (a stalled loop)
DEVICES_LIMIT = 32  # device variables under Cell/Devices: the service has four kinds
STOP_TIMEOUT_S = 5.0

V = ua.VariantType
# each variable's OPC UA type (plant_values says what each holds)
TYPES = {"CellName": V.String, "State": V.String, "Health": V.String, "MountedTool": V.Int32, "RunUnderWay": V.Int64,
         "RunId": V.Int64, "Routine": V.String, "ToolId": V.Int32, "Verdict": V.String, "Evaluation": V.String,
         "ResultCode": V.Int32, "ResultName": V.String, **{name: V.Double for name, _ in FRAME_VARIABLES},
         "PassedGates": V.Boolean, "WrittenBack": V.Boolean, "FinishedAt": V.DateTime}
CELL_VARIABLES = ("CellName", *CELL_NAMES)
EVENT_FIELDS = ("RunId", "Routine", "ToolId", "Verdict", "Evaluation", "ResultCode", "WrittenBack")
LOOPBACK_NAMES = ("localhost",)


class PlantError(Exception):
    """The plant server cannot be served as configured (address taken or invalid, certificate or
    key unreadable): one message naming what and why. The service logs it and runs on."""


def _data_value(value, vtype: ua.VariantType) -> ua.DataValue:
    now = datetime.now(timezone.utc)
    if value is not None:
        return ua.DataValue(ua.Variant(value, vtype), SourceTimestamp=now, ServerTimestamp=now)
    # OPC UA's null is a DataValue without a Variant; asyncua refuses a Null Variant over a typed
    # value, but takes this, and the next typed value after it
    out = ua.DataValue(SourceTimestamp=now, ServerTimestamp=now)
    out.Value = None
    return out


# -- configuration: what start() checks before anything listens ----------------------------------------


@dataclass(frozen=True)
class _Plan:
    endpoint: str
    host: str
    port: int
    policy: ua.SecurityPolicyType
    certificate: tuple[bytes, str] | None  # content, "pem" or "der"
    private_key: tuple[bytes, str] | None
    application_uri: str


def _plan(endpoint: str, cell: str, security: str, certificate: str | None, private_key: str | None) -> _Plan:
    where = f"OPC UA server: cannot listen on {endpoint}"
    url = urlsplit(str(endpoint))
    try:
        port = url.port
    except ValueError:
        raise PlantError(f"{where}: the port is not a number from 1 to 65535") from None
    if url.scheme != "opc.tcp" or not url.hostname:
        raise PlantError(f"{where}: an endpoint is opc.tcp://HOST:PORT (for example opc.tcp://0.0.0.0:4840)")
    if not port:
        raise PlantError(f"{where}: the endpoint names no port (for example opc.tcp://0.0.0.0:4840)")
    if security not in SECURITY:
        raise PlantError(f"OPC UA server: unknown security {security!r}: one of {', '.join(SECURITY)}")
    cert = key = None
    application_uri = f"urn:{socket.gethostname()}:cellcal:{browse_name(cell) or 'cell'}"
    if security != "none":
        if not certificate or not private_key:
            raise PlantError(f"OPC UA server: security {security} needs a certificate and a private key file")
        cert_obj, cert = _read_certificate(certificate)
        key_obj, key = _read_private_key(private_key)
        if key_obj.public_key().public_numbers() != cert_obj.public_key().public_numbers():
            raise PlantError(f"OPC UA server: the private key {private_key} does not belong to the certificate "
                             f"{certificate}")
        application_uri = _certificate_uri(cert_obj) or application_uri
    return _Plan(endpoint, url.hostname, port, SECURITY[security], cert, key, application_uri)


def _read(path: str, what: str) -> tuple[bytes, str]:
    try:
        content = Path(path).read_bytes()
    except OSError as exc:
        raise PlantError(f"OPC UA server: cannot read the {what} {path}: {exc.strerror or exc}") from None
    return content, "pem" if content.lstrip().startswith(b"-----BEGIN") else "der"


def _read_certificate(path: str):
    content, form = _read(path, "certificate")
    try:
        cert = (x509.load_pem_x509_certificate if form == "pem" else x509.load_der_x509_certificate)(content)
    except ValueError:
        raise PlantError(f"OPC UA server: the certificate {path} is not an X.509 certificate in DER or PEM") from None
    if not isinstance(cert.public_key(), rsa.RSAPublicKey):
        raise PlantError(f"OPC UA server: the certificate {path} holds no RSA key (Basic256Sha256 needs one)")
    return cert, (content, form)


def _read_private_key(path: str):
    content, form = _read(path, "private key")
    load = serialization.load_pem_private_key if form == "pem" else serialization.load_der_private_key
    try:
        key = load(content, password=None)
    except (ValueError, TypeError) as exc:
        raise PlantError(f"OPC UA server: the private key {path} is not an RSA key without a password in DER or "
                         f"PEM ({exc})") from None
    if not isinstance(key, rsa.RSAPrivateKey):
        raise PlantError(f"OPC UA server: the private key {path} is not an RSA key (Basic256Sha256 needs one)")
    return key, (content, form)


def _certificate_uri(cert) -> str | None:
    """The application URI a certificate names (clients compare it with the server's)."""
    try:
        names = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    except x509.ExtensionNotFound:
        return None
    uris = names.get_values_for_type(x509.UniformResourceIdentifier)
    return uris[0] if uris else None


def is_loopback(host: str) -> bool:
    """Whether only this PC can reach `host`: localhost, 127.0.0.0/8 or ::1."""
    if host.lower() in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class _Readers:
    """Every session a reader, whatever it logs in with: nobody is the library's administrator,
    who could write any node and add or delete nodes. With `secured`, a session only over a
    channel that carried a client certificate, that is the signed and encrypted one: asyncua
    also lets a session be activated over an unsecured channel when the client ignores the
    endpoints on offer, which would serve in the clear what was meant to be encrypted."""

    def __init__(self, secured: bool):
        self.secured = secured

    def get_user(self, iserver, username=None, password=None, certificate=None) -> User | None:
        if self.secured and not certificate:
            log.warning("OPC UA server: a session over an unsecured channel refused (only %s is served)",
                        "Basic256Sha256_SignAndEncrypt")
            return None
        return User(role=UserRole.User)


def _version() -> str:
    try:
        return metadata.version("cellcal")
    except metadata.PackageNotFoundError:
        return "unknown"


# -- the server --------------------------------------------------------------------------------------------


class OpcuaServer:
    """The cell's OPC UA server for the plant: :meth:`start` it once the service runs, feed it
    :meth:`update_state` and :meth:`publish_result` from any thread, :meth:`stop` it at the end.
    Values given before :meth:`start` (or between a stop and a start) are served from the start."""

    def __init__(self, endpoint: str, cell: str, *, security: str = "none",
                 certificate: str | None = None, private_key: str | None = None):
        self.endpoint, self.cell, self.security = endpoint, cell, security
        self.certificate, self.private_key = certificate, private_key
        self._lock = threading.Lock()  # the fields below, shared by callers' threads and the loop's
        self._state = state_values({})
        self._result = dict(EMPTY_RESULT)
        self._pending: collections.deque = collections.deque()
        self._dropped = 0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._wake: asyncio.Event | None = None
        self._stop: asyncio.Event | None = None
        self._thread: threading.Thread | None = None

    # -- life --------------------------------------------------------------------------------------------

    def start(self, timeout_s: float = 10.0) -> None:
        """Listen on the endpoint; returns once clients can connect. Raises :class:`PlantError`
        (and leaves no thread behind) when the endpoint is invalid or taken, the certificate or
        key unreadable, or the server not up within `timeout_s`. A running server is left as is."""
        if self._thread is not None and self._thread.is_alive():
            return
        plan = _plan(self.endpoint, self.cell, self.security, self.certificate, self.private_key)
        if self.security == "none" and not is_loopback(plan.host):
            log.warning("OPC UA server on %s without security: anyone on the network who can reach the port can "
                        "read the cell's state and results", self.endpoint)
        ready, outcome = threading.Event(), {}
        thread = threading.Thread(target=self._run, args=(plan, ready, outcome), name="cellcal-plant-opcua",
                                  daemon=True)
        thread.start()
        if not ready.wait(timeout_s):
            outcome["abandoned"] = True  # should it come up after all, it stops at once
            self._signal(outcome.get("loop"), outcome.get("stop"))
            thread.join(STOP_TIMEOUT_S)
            raise PlantError(f"OPC UA server: cannot listen on {self.endpoint}: not up within {timeout_s:g} s")
        if "error" in outcome:
            thread.join(STOP_TIMEOUT_S)
            raise PlantError(outcome["error"])
        with self._lock:
            self._loop, self._wake, self._stop = outcome["loop"], outcome["wake"], outcome["stop"]
            self._thread = thread
            # what was given while the server came up, after it had taken its first values
            self._pending.extend([("state", self._state, False), ("result", self._result, False)])
        self._signal(self._loop, self._wake)
        log.info("OPC UA server for the plant on %s (security %s)", self.endpoint, self.security)

    def stop(self) -> None:
        """Stop serving and end the thread; a no-op when not running."""
        with self._lock:
            loop, stop, thread = self._loop, self._stop, self._thread
            self._loop = self._wake = self._stop = self._thread = None
            self._pending.clear()
        if thread is None:
            return
        self._signal(loop, stop)
        thread.join(STOP_TIMEOUT_S)
        if thread.is_alive():
            log.warning("OPC UA server on %s did not stop within %g s (its thread is left to end with the "
                        "service)", self.endpoint, STOP_TIMEOUT_S)

    @staticmethod
    def _signal(loop, event) -> None:
        if loop is None or event is None:
            return
        try:
            loop.call_soon_threadsafe(event.set)
        except RuntimeError:  # the loop has closed already
            pass

    # -- what the service publishes ---------------------------------------------------------------------

    def update_state(self, state: dict) -> None:
        """The cell's live state: ``state``, ``health``, ``mounted_tool``, ``run`` (the run under
        way, or None) and ``devices`` ({name: text}). Never blocks, never raises."""
        try:
            values = state_values(state)
        except Exception:  # a plant interface never takes the caller down
            log.exception("OPC UA server: state not published")
            return
        self._submit("state", values)

    def publish_result(self, run: dict) -> None:
        """A finished run (the JSON API's run dict): sets LastResult and fires ResultReady. Never
        blocks, never raises."""
        try:
            values = result_values(run)
        except Exception:
            log.exception("OPC UA server: result not published")
            return
        self._submit("result", values)

    def _submit(self, kind: str, values) -> None:
        with self._lock:
            if kind == "state":
                self._state = values
            else:
                self._result = values
            loop, wake = self._loop, self._wake
            if loop is None:
                return
            self._pending.append((kind, values, kind == "result"))
            if len(self._pending) > PENDING_LIMIT:
                self._pending.popleft()
                self._dropped += 1
        self._signal(loop, wake)

    # -- the loop's side ----------------------------------------------------------------------------------

    def _run(self, plan: _Plan, ready: threading.Event, outcome: dict) -> None:
        loop = asyncio.new_event_loop()
        try:
            loop.run_until_complete(self._serve(plan, ready, outcome))
        except Exception as exc:  # after start: logged, the service runs on without the plant server
            if not ready.is_set():
                outcome["error"] = f"OPC UA server: cannot listen on {self.endpoint}: {exc}"
                ready.set()
            else:
                log.exception("OPC UA server on %s stopped", self.endpoint)
        finally:
            loop.close()

    async def _serve(self, plan: _Plan, ready: threading.Event, outcome: dict) -> None:
        outcome.update(loop=asyncio.get_running_loop(), wake=asyncio.Event(), stop=asyncio.Event())
        server = Server(user_manager=_Readers(secured=plan.policy != ua.SecurityPolicyType.NoSecurity))
        try:
            await _probe(plan)
            space = await self._build(server, plan)
            await server.start()
        except Exception as exc:
            outcome["error"] = exc.args[0] if isinstance(exc, PlantError) else \
                f"OPC UA server: cannot listen on {self.endpoint}: {_reason(exc)}"
            await _quietly(server.stop())
            ready.set()
            return
        with self._lock:
            state, result = self._state, self._result
        await space.apply_state(state)
        await space.apply_result(result, fire=False)
        ready.set()
        wake, stop = outcome["wake"], outcome["stop"]
        if outcome.get("abandoned"):
            stop.set()
        stopping = asyncio.ensure_future(stop.wait())
        try:
            while not stop.is_set():
                woken = asyncio.ensure_future(wake.wait())
                await asyncio.wait({woken, stopping}, return_when=asyncio.FIRST_COMPLETED)
                woken.cancel()
                wake.clear()
                await self._apply_pending(space)
        finally:
            stopping.cancel()
            await _quietly(server.stop())

    async def _apply_pending(self, space: _AddressSpace) -> None:
        with self._lock:
            pending, self._pending = list(self._pending), collections.deque()
            dropped, self._dropped = self._dropped, 0
        if dropped:
            log.warning("OPC UA server: %d updates dropped (the server fell behind)", dropped)
        for kind, values, fire in pending:
            try:
                if kind == "state":
                    await space.apply_state(values)
                else:
                    await space.apply_result(values, fire=fire)
            except Exception:
                log.exception("OPC UA server: %s not published", kind)

    async def _build(self, server: Server, plan: _Plan) -> _AddressSpace:
        await server.init()
        server.set_endpoint(plan.endpoint)
        server.set_server_name(f"cellcal {self.cell}")
        server.product_uri, server.manufacturer_name = "urn:cellcal", "cellcal"
        await server.set_application_uri(plan.application_uri)
        await server.set_build_info("urn:cellcal", "cellcal", f"cellcal {self.cell}", _version(), _version(),
                                    datetime.now(timezone.utc))
        server.allow_remote_admin(False)
        server.set_identity_tokens([ua.AnonymousIdentityToken])
        server.set_security_policy([plan.policy])
        if plan.certificate is not None:
            await server.load_certificate(plan.certificate[0], plan.certificate[1])
            await server.load_private_key(plan.private_key[0], None, plan.private_key[1])
        space = _AddressSpace(server)
        await space.build(self.cell)
        return space


async def _probe(plan: _Plan) -> None:
    """Bind the endpoint's address once and let go, so a taken port is one PlantError rather than
    the library's logged traceback first."""
    probe = await asyncio.get_running_loop().create_server(asyncio.Protocol, plan.host, plan.port)
    probe.close()
    await probe.wait_closed()


def _reason(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.errno == errno.EADDRINUSE:
        return "the port is taken (another program listens on it)"
    if isinstance(exc, socket.gaierror):
        return f"no such host ({exc.strerror})"
    if isinstance(exc, OSError) and exc.errno == errno.EADDRNOTAVAIL:
        return "the address is none of this PC's"
    if isinstance(exc, OSError) and exc.errno == errno.EACCES:
        return "permission denied (ports below 1024 need privileges)"
    return (exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)) or type(exc).__name__


async def _quietly(coro) -> None:
    try:
        await coro
    except Exception:  # stopping a server that never fully started
        log.debug("OPC UA server: stopping", exc_info=True)


class _AddressSpace:
    """The nodes of namespace urn:cellcal:plant, and writing values to them on the server's loop."""

    def __init__(self, server: Server):
        self.server = server
        self.idx = 0
        self.cell_node = self.devices_node = None
        self.variables: dict[str, tuple] = {}  # browse path below Cell -> (node, variant type)
        self.device_names: set[str] = set()
        self.events = None

    async def build(self, cell: str) -> None:
        self.idx = idx = await self.server.register_namespace(NAMESPACE_URI)
        objects = self.server.nodes.objects
        self.cell_node = await objects.add_object(ua.NodeId("Cell", idx), ua.QualifiedName("Cell", idx))
        for name in CELL_VARIABLES:
            await self._variable(self.cell_node, "Cell", name, TYPES[name])
        await self._write("CellName", text(cell))
        self.devices_node = await self.cell_node.add_object(ua.NodeId("Cell.Devices", idx),
                                                            ua.QualifiedName("Devices", idx))
        last = await self.cell_node.add_object(ua.NodeId("Cell.LastResult", idx), ua.QualifiedName("LastResult", idx))
        for name in RESULT_NAMES:
            await self._variable(last, "Cell.LastResult", name, TYPES[name], key=f"LastResult.{name}")
        base = self.server.get_node(ua.ObjectIds.BaseEventType)
        event_type = await base.add_object_type(ua.NodeId("ResultReadyEventType", idx),
                                                ua.QualifiedName("ResultReadyEventType", idx))
        for name in EVENT_FIELDS:
            await event_type.add_property(ua.NodeId(f"ResultReadyEventType.{name}", idx), ua.QualifiedName(name, idx),
                                          ua.get_default_value(TYPES[name]), varianttype=TYPES[name])
        self.events = await self.server.get_event_generator(event_type, self.cell_node)

    async def _variable(self, parent, parent_path: str, name: str, vtype: ua.VariantType, key: str | None = None):
        node = await parent.add_variable(ua.NodeId(f"{parent_path}.{name}", self.idx), ua.QualifiedName(name, self.idx),
                                         ua.Variant(None, ua.VariantType.Null), datatype=ua.NodeId(vtype.value))
        read_only = ua.DataValue(ua.Variant(ua.AccessLevel.CurrentRead.mask, ua.VariantType.Byte))
        await node.write_attribute(ua.AttributeIds.AccessLevel, read_only)
        await node.write_attribute(ua.AttributeIds.UserAccessLevel, read_only)
        self.variables[key or name] = (node, vtype)
        return node

    async def _write(self, key: str, value) -> None:
        node, vtype = self.variables[key]
        await self.server.write_attribute_value(node.nodeid, _data_value(value, vtype))

    async def apply_state(self, values: tuple[dict, dict]) -> None:
        cell, devices = values
        for name, value in cell.items():
            await self._write(name, value)
        for name in sorted(set(devices) - self.device_names):
            if len(self.device_names) >= DEVICES_LIMIT:
                break
            await self._variable(self.devices_node, "Cell.Devices", name, ua.VariantType.String, key=f"Devices.{name}")
            self.device_names.add(name)
        for name in self.device_names:  # a device the service no longer names reads null
            await self._write(f"Devices.{name}", devices.get(name))

    async def apply_result(self, values: dict, fire: bool) -> None:
        for name, value in values.items():
            await self._write(f"LastResult.{name}", value)
        if not fire:
            return
        event = self.events.event
        for name in EVENT_FIELDS:
            setattr(event, name, values[name])
        event.Severity = 100 if values["Evaluation"] == "OK" else 500
        run = "run" if values["RunId"] is None else f"run {values['RunId']}"
        await self.events.trigger(time_attr=values["FinishedAt"],
                                  message=f"{run} {values['Routine'] or ''}: {values['Evaluation']}")
