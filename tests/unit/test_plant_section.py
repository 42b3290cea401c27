"""The cell file's ``plant`` section: read as written, off when absent, and every bad entry refused at load with
one message naming the file, the section and the key (a password in the cell file, a secret file others can
read, a TLS file missing or unreadable, an unknown key, a topic with wildcards, a malformed endpoint)."""
from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import pytest

from cellcal.config.cells import CellFileError, MqttSpec, OpcuaSpec
from cellcal.daemon.cells import load_cell
from support.cell_edits import edited_cell


def _secret(folder, name="password", mode=0o600, text="s3cret\n"):
    path = folder / name
    path.write_text(text)
    path.chmod(mode)
    return path


def _load(tmp_path, plant):
    return load_cell(edited_cell(tmp_path, "sim", {"plant": plant}))


def test_a_cell_file_without_the_section_publishes_nothing(tmp_path):
    cell = load_cell(edited_cell(tmp_path, "sim"))
    assert cell.plant.mqtt is None and cell.plant.opcua is None


def test_the_section_as_written_files_taken_from_the_cell_files_folder(tmp_path):
    _secret(tmp_path)
    _secret(tmp_path, "ca.pem", 0o644, "-----BEGIN CERTIFICATE-----\n")
    cell = _load(tmp_path, {"mqtt": {"host": "broker", "port": 8883, "topic": "plant/line1/cell7", "username": "c7",
                                     "password_file": "password", "tls": {"ca": "ca.pem"}},
                            "opcua": {"endpoint": "opc.tcp://127.0.0.1:4840/cellcal/"}})
    assert cell.plant.mqtt == MqttSpec(host="broker", port=8883, topic="plant/line1/cell7", client_id=cell.name,
                                       username="c7", password_file=str((tmp_path / "password").resolve()),
                                       tls_ca=str((tmp_path / "ca.pem").resolve()))
    assert cell.plant.opcua == OpcuaSpec(endpoint="opc.tcp://127.0.0.1:4840/cellcal/")


@pytest.mark.parametrize("plant, key, words", [
    ({"mqtt": {"host": "b", "topic": "t", "password": "hunter2"}}, "plant.mqtt.password", "password_file"),
    ({"mqtt": {"host": "b", "topic": "t", "colour": 1}}, "plant.mqtt.colour", "unknown key"),
    ({"mqtt": {"topic": "t"}}, "plant.mqtt", "host"),
    ({"mqtt": {"host": "b", "topic": "plant/#"}}, "plant.mqtt.topic", "wildcard"),
    ({"mqtt": {"host": "b", "topic": "/plant"}}, "plant.mqtt.topic", "leading"),
    ({"mqtt": {"host": "b", "topic": "t", "port": 0}}, "plant.mqtt.port", ""),
    ({"mqtt": {"host": "b", "topic": "t", "tls": {"ca": "missing.pem"}}}, "plant.mqtt.tls.ca", "no such file"),
    ({"mqtt": {"host": "b", "topic": "t", "tls": {"ca": "ca.pem", "cert": "ca.pem"}}}, "plant.mqtt.tls.key",
     "together"),
    ({"mqtt": {"host": "b", "topic": "t", "password_file": "password"}}, "plant.mqtt.password_file", "username"),
    ({"mqtt": {"host": "b", "topic": "t", "username": "u", "password_file": "open-password"}},
     "plant.mqtt.password_file", "chmod 600"),
    ({"opcua": {"endpoint": "http://127.0.0.1:4840"}}, "plant.opcua.endpoint", "opc.tcp://HOST:PORT/PATH"),
    ({"opcua": {"endpoint": "opc.tcp://127.0.0.1:4840/", "security": "Basic128"}}, "plant.opcua.security", ""),
    ({"opcua": {"endpoint": "opc.tcp://127.0.0.1:4840/", "security": "Basic256Sha256_SignAndEncrypt"}},
     "plant.opcua.certificate", "certificate and private_key"),
    ({"opc": {}}, "plant.opc", "unknown key"),
])
def test_a_bad_plant_section_is_refused_naming_the_key(tmp_path, plant, key, words):
    _secret(tmp_path)
    _secret(tmp_path, "open-password", 0o644)
    _secret(tmp_path, "ca.pem", 0o644, "-----BEGIN CERTIFICATE-----\n")
    with pytest.raises(CellFileError) as refused:
        _load(tmp_path, plant)
    assert f"[{key}" in str(refused.value) and words in str(refused.value), str(refused.value)


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads any file (the root-only case below covers it)")
def test_an_unreadable_tls_file_is_refused_naming_it(tmp_path):
    ca = _secret(tmp_path, "ca.pem", 0o000)
    with pytest.raises(CellFileError) as refused:
        _load(tmp_path, {"mqtt": {"host": "b", "topic": "t", "tls": {"ca": "ca.pem"}}})
    assert "[plant.mqtt.tls.ca]" in str(refused.value) and "cannot be read" in str(refused.value)
    ca.chmod(0o600)


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root to make a file only root can read and load as another user")
def test_a_tls_file_the_service_user_cannot_read_is_refused_naming_it():
    from support.users import as_nobody

    top = Path(tempfile.mkdtemp(prefix="cellcal-plant-"))  # not under pytest's root-only 0700 folder
    try:
        top.chmod(0o755)
        (top / "ca.pem").write_text("-----BEGIN CERTIFICATE-----\n")
        (top / "ca.pem").chmod(0o600)  # root's: the service's user (nobody here) cannot read it
        path = edited_cell(top, "sim", {"plant": {"mqtt": {"host": "b", "topic": "t", "tls": {"ca": "ca.pem"}}}})
        path.chmod(0o644)
        answer = as_nobody(lambda: load_cell(path), CellFileError)
        assert "[plant.mqtt.tls.ca]" in answer and f"{top / 'ca.pem'}: cannot be read" in answer, answer
    finally:
        shutil.rmtree(top)
