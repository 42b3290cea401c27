"""How ``cellcal daemon`` serves its status page (cli/daemon.py ``_serve_status_page``): on,
off with one key, a line in the log when bound beyond this PC, and a taken port costs the
page only, never the service."""
from __future__ import annotations

import json
import logging
import socket
import urllib.request
from dataclasses import replace
from types import SimpleNamespace

import pytest

from cellcal.cli.daemon import _serve_status_page
from cellcal.daemon.cells import load_cell


def status() -> dict:
    return {"state": "idle", "run_id": None}


@pytest.fixture
def cell():
    return load_cell("sim")


def on(cell, **keys):
    return SimpleNamespace(status_page=replace(cell.status_page, **keys), tools=cell.tools, path=cell.path)


def test_the_page_is_served_on_the_cell_files_address_and_stops(cell, loopback_host, tmp_path, caplog):
    caplog.set_level(logging.INFO, logger="cellcal.daemon")
    with socket.socket() as probe:  # a free port on the test's own loopback address
        probe.bind((loopback_host, 0))
        port = probe.getsockname()[1]
    server = _serve_status_page(on(cell, host=loopback_host, port=port), SimpleNamespace(status=status), tmp_path)
    try:
        with urllib.request.urlopen(f"http://{loopback_host}:{port}/api/v1/state", timeout=5) as answer:
            assert json.load(answer)["state"] == "idle"
        assert f"status page and JSON API (read-only): http://{loopback_host}:{port}/" in caplog.text
        assert "beyond this PC" not in caplog.text  # loopback: no warning
    finally:
        server.stop()


def test_off_with_one_key(cell, tmp_path, caplog):
    caplog.set_level(logging.INFO, logger="cellcal.daemon")
    assert _serve_status_page(on(cell, enabled=False), SimpleNamespace(status=status), tmp_path) is None
    assert "status page: off" in caplog.text


def test_a_taken_port_costs_the_page_only(cell, loopback_host, tmp_path, caplog):
    with socket.socket() as taken:
        taken.bind((loopback_host, 0))
        taken.listen()
        port = taken.getsockname()[1]
        served = _serve_status_page(on(cell, host=loopback_host, port=port), SimpleNamespace(status=status),
                                    tmp_path)
    assert served is None
    assert "status page not served" in caplog.text and "the service runs on without it" in caplog.text


def test_an_address_beyond_this_pc_is_said_in_the_log(cell, tmp_path, caplog, monkeypatch):
    """Served on every interface (as a cell file with host 0.0.0.0 asks): a warning line. The
    server is a stand-in here: the test binds nothing beyond loopback."""
    import cellcal.daemon.status_server as status_server

    class Listening:
        def __init__(self, status, state_dir, spec, tool_names=None, tool_bands=None):
            self.url = f"http://{spec.host}:{spec.port}/"

        def start(self):
            return self

    monkeypatch.setattr(status_server, "StatusServer", Listening)
    caplog.set_level(logging.INFO, logger="cellcal.daemon")
    assert _serve_status_page(on(cell, host="0.0.0.0"), SimpleNamespace(status=status), tmp_path) is not None
    warning = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warning) == 1 and "served on 0.0.0.0:8037, beyond this PC" in warning[0].getMessage()


@pytest.mark.parametrize("keys, words", [
    ({"port": 0}, "[status_page.port]"),
    ({"port": 70000}, "[status_page.port]"),
    ({"enabled": "yes"}, "[status_page.enabled]"),
    ({"max_connections": 0}, "[status_page.max_connections]"),
    ({"rate_per_s": -1}, "[status_page.rate_per_s]"),
    ({"prot": 8037}, "[status_page.prot]"),
])
def test_a_bad_status_page_section_is_refused_naming_the_key(tmp_path, keys, words):
    from support.cell_edits import edited_cell
    from cellcal.config.cells import CellFileError
    path = edited_cell(tmp_path, "sim", {"status_page": keys})
    with pytest.raises(CellFileError) as refused:
        load_cell(path)
    assert words in str(refused.value) and str(path) in str(refused.value)
