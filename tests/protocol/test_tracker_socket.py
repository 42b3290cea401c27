"""The tracker's TCP line protocol: the socket client against the simulated tracker server."""
import time

import numpy as np
import pytest

from cellcal.drivers.interfaces import DeviceError, DeviceTimeout, ProtocolError
from cellcal.drivers.registry import DriverConfigError
from cellcal.drivers.tracker_socket import TrackerSocket, TrackerStatusError, with_checksum
from cellcal.sims.physics.kinematic_arm import TrackerNoise
from cellcal.sims.net.tracker_server import TrackerServer

MARGIN_S = 2.0  # scheduling slack on top of a deadline: a 2-core machine with both cores busy wakes a waiter late
SMR1_M = np.array([1.2, -2.0, 0.4])


@pytest.fixture
def server():
    targets = {"smr1": SMR1_M}
    with TrackerServer(targets.get, rng=np.random.default_rng(7)) as srv:
        yield srv


@pytest.fixture
def tracker(server):
    tracker = TrackerSocket(port=server.port)
    yield tracker
    tracker.close()


# --- measurements ---------------------------------------------------------------------

def test_measurements_scatter_with_the_at960_noise_model(tracker):
    n = 400
    points = np.array([tracker.measure("smr1").position_m for _ in range(n)])
    distance_m = np.linalg.norm(SMR1_M)
    sigma_m = (15e-6 + 6e-6 * distance_m)  # 15 um + 6 um/m, per axis
    assert np.allclose(points.mean(axis=0), SMR1_M, atol=5 * sigma_m / np.sqrt(n))
    # the sample std of 400 normal draws is within 15 % of the true one (>4 sigma)
    assert np.allclose(points.std(axis=0, ddof=1), sigma_m, rtol=0.15)


def test_reply_carries_instrument_sigma_time_and_status(server, tracker):
    first = tracker.measure("smr1")
    second = tracker.measure("smr1")
    expected_sigma_m = TrackerNoise().sigma(SMR1_M[None] * 1000)[0] / 1000
    assert first.quality == pytest.approx(expected_sigma_m, rel=1e-3)
    assert first.status == "ok" and first.orientation is None
    assert 0 < first.t_s < second.t_s
    server.status = "unstable"
    assert tracker.measure("smr1").status == "unstable"


def test_six_dof_target_reports_its_orientation():
    quaternion = np.array([np.cos(0.2), 0.0, np.sin(0.2), 0.0])
    with TrackerServer(lambda t: SMR1_M, orientation_fn=lambda t: quaternion) as server:
        tracker = TrackerSocket(port=server.port)
        m = tracker.measure("tmac")
        assert np.allclose(m.orientation, quaternion, atol=1e-9)
        assert np.allclose(m.position_m, SMR1_M, atol=1e-3)
        tracker.close()


def test_unknown_target_is_status_error_code_2(tracker):
    with pytest.raises(TrackerStatusError) as err:
        tracker.measure("smr9")
    assert err.value.code == 2
    assert "target not found (code 2) on MEAS smr9 1: no target smr9 in view" in str(err.value)


def test_broken_beam_is_status_error_code_1(server, tracker):
    server.beam_broken = True
    with pytest.raises(TrackerStatusError) as err:
        tracker.measure("smr1")
    assert err.value.code == 1 and "beam broken (code 1)" in str(err.value)
    server.beam_broken = False
    assert np.allclose(tracker.measure("smr1").position_m, SMR1_M, atol=1e-3)


def test_target_name_outside_the_protocol_is_refused_before_sending(server, tracker):
    with pytest.raises(ValueError, match="target name 'smr 1'"):
        tracker.measure("smr 1")
    assert server.requests == []


def test_bad_port_option_is_refused_naming_it():
    with pytest.raises(DriverConfigError) as refused:
        TrackerSocket(port=0)
    assert refused.value.key == "port" and refused.value.problem.startswith("0 "), refused.value


# --- failures ---------------------------------------------------------------------------

def test_connection_refused_names_the_tracker(loopback_host):
    host, port = loopback_host, 5030  # an address of the test's own: nothing listens there
    with pytest.raises(DeviceError) as err:
        TrackerSocket(host, port=port)
    assert type(err.value) is DeviceError
    assert str(err.value) == f"tracker ({host}:{port}): cannot connect: Connection refused"


def test_connection_lost_mid_measurement_is_named_and_reopened(server, tracker):
    tracker.measure("smr1")
    server.silent = True
    server.drop_connections()
    with pytest.raises(DeviceError) as err:
        tracker.measure("smr1", timeout_s=2.0)
    assert type(err.value) is DeviceError
    assert "connection lost" in str(err.value) and "MEAS smr1 2" in str(err.value)
    server.silent = False
    assert np.allclose(tracker.measure("smr1").position_m, SMR1_M, atol=1e-3)


def test_no_reply_times_out_within_the_deadline_and_late_reply_is_skipped(server, tracker):
    server.reply_delay_s, timeout_s = 0.4, 0.15
    started = time.monotonic()
    with pytest.raises(DeviceTimeout) as err:
        tracker.measure("smr1", timeout_s=timeout_s)
    assert timeout_s <= time.monotonic() - started < timeout_s + MARGIN_S  # at its deadline, never before
    assert "no reply to MEAS smr1 1 within 0.15 s" in str(err.value)
    server.reply_delay_s = 0.0
    # the reply to request 1 arrives late, ahead of the one to request 2, and is skipped
    assert tracker.measure("smr1", timeout_s=2.0).status == "ok"
    assert server.requests == ["MEAS smr1 1", "MEAS smr1 2"]


def test_bad_checksum_reply_is_a_protocol_error(server, tracker):
    server.inject_reply(b"OK 1 ok 0.1 1.0 2.0 3.0 1e-5*00\r\n")
    with pytest.raises(ProtocolError, match="bad checksum: line says 00, computed 5C"):
        tracker.measure("smr1")


def test_truncated_reply_is_a_protocol_error(server, tracker):
    server.inject_reply(with_checksum("OK 1 ok 0.1 1.0 2.0"))
    with pytest.raises(ProtocolError, match="malformed OK reply: 6 fields, expected 8"):
        tracker.measure("smr1")
    server.inject_reply(b"OK 2 ok 0.1 1.0 2.0 3.0 1e-5\r\n")  # no checksum at all
    with pytest.raises(ProtocolError, match=r"truncated line \(no checksum\)"):
        tracker.measure("smr1")


def test_reply_to_another_request_is_a_protocol_error(server, tracker):
    server.inject_reply(with_checksum("OK 77 ok 0.1 1.0 2.0 3.0 1e-5"))
    with pytest.raises(ProtocolError, match="reply to request 77 while waiting for MEAS smr1 1"):
        tracker.measure("smr1")


def test_endless_reply_line_is_refused_without_hanging(server, tracker):
    server.inject_reply(b"OK " + b"9" * 2000)
    timeout_s = 4 * MARGIN_S
    started = time.monotonic()
    with pytest.raises(ProtocolError, match="reply longer than 512 bytes without terminator"):
        tracker.measure("smr1", timeout_s=timeout_s)
    # refused on its length, not at the timeout: half of it leaves a loaded machine room and tells the two apart
    assert time.monotonic() - started < timeout_s / 2
    assert np.allclose(tracker.measure("smr1").position_m, SMR1_M, atol=1e-3)  # reconnected
