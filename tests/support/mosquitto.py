"""A real Mosquitto broker for the plant tests: Debian's ``mosquitto`` package, started on a free loopback port
with a configuration of the test's own (``make test`` installs the package when root; elsewhere the tests skip
and say what is missing)."""
from __future__ import annotations

import getpass
import json
import shutil
import socket
import subprocess
import threading
import time
from pathlib import Path

import paho.mqtt.client as mqtt
import pytest


def mosquitto_or_skip() -> str:
    path = shutil.which("mosquitto") or ("/usr/sbin/mosquitto" if Path("/usr/sbin/mosquitto").exists() else None)
    if path is None:
        pytest.skip("no `mosquitto`: the plant tests need Debian's mosquitto package "
                    "(`apt-get install --no-install-recommends mosquitto`, which `make test` does as root)")
    return path


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Broker:
    """One broker process on 127.0.0.1:port; ``stop`` and ``start`` again keep the port and the persistence file
    (a broker restarted), ``users`` {name: password} turns anonymous access off."""

    def __init__(self, folder: Path, users: dict | None = None, tls: dict | None = None):
        """tls: {"ca", "cert", "key"} of the broker's listener (files), clients' certificates required."""
        self.exe = mosquitto_or_skip()
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.port = free_port()
        # run as this user (started as root, mosquitto would turn into user "mosquitto", who cannot read the
        # test's private folder)
        lines = [f"listener {self.port} 127.0.0.1", f"user {getpass.getuser()}", "persistence true",
                 f"persistence_location {self.folder}/", "autosave_interval 1", "max_queued_messages 100000",
                 "log_dest none"]
        if users:
            passwd = self.folder / "passwd"
            passwd.write_text("")
            for name, password in users.items():
                subprocess.run([shutil.which("mosquitto_passwd") or "mosquitto_passwd", "-b", str(passwd), name,
                                password], check=True, capture_output=True)
            lines += ["allow_anonymous false", f"password_file {passwd}"]
        else:
            lines += ["allow_anonymous true"]
        if tls:
            lines += [f"cafile {tls['ca']}", f"certfile {tls['cert']}", f"keyfile {tls['key']}",
                      "require_certificate true"]
        self.conf = self.folder / "mosquitto.conf"
        self.conf.write_text("\n".join(lines) + "\n")
        self.process: subprocess.Popen | None = None

    def start(self, timeout_s: float = 10.0) -> "Broker":
        self.process = subprocess.Popen([self.exe, "-c", str(self.conf)], stdout=subprocess.DEVNULL,
                                        stderr=subprocess.PIPE)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"mosquitto exited: {self.process.stderr.read().decode(errors='replace')}")
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=0.2):
                    return self
            except OSError:
                time.sleep(0.05)
        raise RuntimeError(f"mosquitto did not listen on {self.port} within {timeout_s} s")

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self.process = None


class Subscriber:
    """A plant consumer: a persistent session (the broker keeps its messages while it is away), QoS 1."""

    def __init__(self, port: int, topic: str, name: str = "consumer"):
        self.topic = topic
        self.messages: list[tuple[str, dict]] = []
        self.lock = threading.Lock()
        self.client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=name, clean_session=False)
        self.client.on_connect = lambda c, u, f, rc, p=None: c.subscribe(topic + "/#", qos=1)
        self.client.on_message = self._on_message
        self.client.reconnect_delay_set(1, 2)
        self.client.connect("127.0.0.1", port)
        self.client.loop_start()

    def _on_message(self, client, userdata, msg) -> None:
        with self.lock:
            self.messages.append((msg.topic, json.loads(msg.payload)))

    def runs(self) -> list[dict]:
        with self.lock:
            return [doc for topic, doc in self.messages if "/runs/" in topic]

    def unique_runs(self) -> list[dict]:
        """The runs as a plant consumer keeps them: repeats of (topic, run id) dropped, the first arrival kept,
        in the order they arrived (delivery is at least once: docs/plant.md)."""
        first: dict[tuple[str, int], dict] = {}
        for doc in self.runs():
            first.setdefault((doc["topic"], doc["id"]), doc)
        return list(first.values())

    def states(self) -> list[dict]:
        with self.lock:
            return [doc for topic, doc in self.messages if topic == self.topic + "/state"]

    def wait(self, until, timeout_s: float = 20.0) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if until():
                return
            time.sleep(0.05)
        raise AssertionError(f"not within {timeout_s} s: runs {[r['id'] for r in self.runs()]}")

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


class DropProxy:
    """A TCP relay in front of the broker whose connections the test can cut (``drop``): a broker that accepted
    a client and then loses it mid-publish, the broker itself running on (its other clients unaffected)."""

    def __init__(self, target_port: int):
        self.target = target_port
        self.server = socket.socket()
        self.server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.server.bind(("127.0.0.1", 0))
        self.server.listen(8)
        self.port = self.server.getsockname()[1]
        self.pairs: list[tuple[socket.socket, socket.socket]] = []
        self.lock = threading.Lock()
        self.closed = False
        self.holding = threading.Event()  # set: what clients send is swallowed (a connection gone dead)
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while not self.closed:
            try:
                client, _ = self.server.accept()
            except OSError:
                return
            try:
                upstream = socket.create_connection(("127.0.0.1", self.target))
            except OSError:
                client.close()
                continue
            with self.lock:
                self.pairs.append((client, upstream))
            for a, b, outward in ((client, upstream, True), (upstream, client, False)):
                threading.Thread(target=self._pipe, args=(a, b, outward), daemon=True).start()

    def _pipe(self, a: socket.socket, b: socket.socket, outward: bool) -> None:
        try:
            while data := a.recv(65536):
                if outward and self.holding.is_set():
                    continue  # never reaches the broker: nothing of it is acknowledged
                b.sendall(data)
        except OSError:
            pass
        for s in (a, b):
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    def hold(self) -> None:
        """The connections go dead without closing: what the clients send from now on is lost."""
        self.holding.set()

    def drop(self) -> None:
        """Cut every connection through the relay, as a network that fails does (and forward again after)."""
        with self.lock:
            pairs, self.pairs = self.pairs, []
        self.holding.clear()
        for pair in pairs:
            for s in pair:
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                s.close()

    def close(self) -> None:
        self.closed = True
        self.server.close()
        self.drop()


def certificates(folder: Path) -> dict:
    """A test CA, and a server (CN 127.0.0.1, also as IP) and a client certificate it signed, made with Debian's
    ``openssl``: {"ca", "server_cert", "server_key", "client_cert", "client_key"} (paths; keys mode 600)."""
    openssl = shutil.which("openssl")
    if openssl is None:
        pytest.skip("no `openssl` to make the test's certificates (Debian's openssl package)")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)

    def run(*args):
        subprocess.run([openssl, *args], check=True, capture_output=True, cwd=folder)

    run("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2", "-keyout", "ca.key", "-out", "ca.pem",
        "-subj", "/CN=cellcal test CA")
    for name, cn in (("server", "127.0.0.1"), ("client", "cell7")):
        run("req", "-newkey", "rsa:2048", "-nodes", "-keyout", f"{name}.key", "-out", f"{name}.csr", "-subj", f"/CN={cn}")
        (folder / f"{name}.ext").write_text("subjectAltName=IP:127.0.0.1\n" if name == "server" else "\n")
        run("x509", "-req", "-in", f"{name}.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial", "-days",
            "2", "-out", f"{name}.pem", "-extfile", f"{name}.ext")
        (folder / f"{name}.key").chmod(0o600)
    return {"ca": str(folder / "ca.pem"), "server_cert": str(folder / "server.pem"),
            "server_key": str(folder / "server.key"), "client_cert": str(folder / "client.pem"),
            "client_key": str(folder / "client.key")}
