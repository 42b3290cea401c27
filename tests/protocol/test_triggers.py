"""Trigger events over Modbus TCP, a serial line and CAN: each real client library
against a fake that speaks the device's protocol."""
import time
import uuid

import pytest

from cellcal.drivers.triggers.can_bus import CanTrigger
from cellcal.drivers.interfaces import DeviceError, DeviceTimeout, Edge, ProtocolError
from cellcal.drivers.modbus.trigger import ModbusTrigger
from cellcal.drivers.triggers.serial_line import SerialTrigger
from cellcal.sims.net.can_barrier import CanBarrier
from cellcal.sims.net.modbus_server import ModbusCellServer
from cellcal.sims.net.serial_barrier import SerialBarrier

MARGIN_S = 2.0  # scheduling slack on top of a deadline: a 2-core machine with both cores busy wakes a waiter late
WAIT_S = 2.0  # generous: returns as soon as the first event is there


class ModbusHarness:
    def __init__(self, ring_size=16):
        self.server = ModbusCellServer(ring_size=ring_size).start()
        self.trigger = ModbusTrigger(port=self.server.port, poll_interval_s=0.002)

    def send(self, channel, edge, t_us):
        self.server.record_edge(channel, edge, t_us)

    def close(self):
        self.trigger.close()
        self.server.stop()


class SerialHarness:
    def __init__(self):
        self.barrier = SerialBarrier()
        self.trigger = SerialTrigger(self.barrier.tty_path)

    def send(self, channel, edge, t_us, **kw):
        self.barrier.send_edge(channel, edge, t_us, **kw)

    def close(self):
        self.trigger.close()
        self.barrier.close()


class CanHarness:
    def __init__(self):
        channel = f"cellcal-test-{uuid.uuid4().hex}"  # a bus of its own per test
        self.trigger = CanTrigger(channel, interface="virtual")
        self.barrier = CanBarrier(channel)

    def send(self, channel, edge, t_us, **kw):
        self.barrier.send_edge(channel, edge, t_us, **kw)

    def close(self):
        self.trigger.close()
        self.barrier.close()


HARNESSES = {"modbus": ModbusHarness, "serial": SerialHarness, "can": CanHarness}


@pytest.fixture(params=sorted(HARNESSES))
def link(request):
    harness = HARNESSES[request.param]()
    yield harness
    harness.close()


@pytest.fixture
def serial_link():
    harness = SerialHarness()
    yield harness
    harness.close()


@pytest.fixture
def can_link():
    harness = CanHarness()
    yield harness
    harness.close()


def collect(trigger, n, timeout_s=WAIT_S):
    events, deadline = [], time.monotonic() + timeout_s
    while len(events) < n and time.monotonic() < deadline:
        events += trigger.events(timeout_s=0.05)
    return events


# --- round trips, every transport ------------------------------------------------------

def test_edges_round_trip_with_device_time_to_1_us(link):
    # across the device clock's 32-bit wrap: 4294967295 us -> 0
    sent = [(0, Edge.BLOCKED, 4_294_966_000), (1, Edge.CLEARED, 4_294_967_295),
            (7, Edge.BLOCKED, 3), (255, Edge.CLEARED, 1_234_567)]
    for channel, edge, t_us in sent:
        link.send(channel, edge, t_us)
    events = collect(link.trigger, len(sent))
    first = sent[0][2]
    unwrapped_us = [first, 4_294_967_295, 2**32 + 3, 2**32 + 1_234_567]
    assert [(e.channel, e.edge) for e in events] == [(c, e) for c, e, _ in sent]
    assert [round(e.t_s * 1e6) for e in events] == unwrapped_us
    assert max(abs(e.t_s * 1e6 - u) for e, u in zip(events, unwrapped_us)) < 1e-3
    assert all(e.device_time for e in events)


def test_no_edges_returns_nothing_at_the_deadline(link):
    timeout_s = 0.2
    started = time.monotonic()
    assert link.trigger.events(timeout_s=timeout_s) == []
    assert timeout_s <= time.monotonic() - started < timeout_s + MARGIN_S  # at its deadline, never before


def test_out_of_order_timestamp_is_refused_and_earlier_events_kept(link):
    link.send(2, Edge.BLOCKED, 50_000)
    link.send(2, Edge.CLEARED, 49_000)  # the device clock went back 1 ms
    handed, deadline = [], time.monotonic() + WAIT_S
    with pytest.raises(ProtocolError) as err:
        while time.monotonic() < deadline:
            handed += link.trigger.events(timeout_s=0.05)
    assert "timestamp out of order" in str(err.value)
    assert "at 49000 us after 50000 us (channel 2)" in str(err.value)
    assert err.value.device.startswith("trigger (")
    # the edge before the fault is never lost: handed over by a call before the one that met the fault (the two
    # sentences arrived apart), or kept for the next call (they arrived together)
    kept = handed + link.trigger.events()
    assert [(e.edge, round(e.t_s * 1e6)) for e in kept] == [(Edge.BLOCKED, 50_000)]
    # the stream restarts: later edges are accepted again
    link.send(2, Edge.BLOCKED, 60_000)
    assert [round(e.t_s * 1e6) for e in collect(link.trigger, 1)] == [60_000]


def test_equal_timestamps_on_two_channels_are_in_order(link):
    link.send(0, Edge.BLOCKED, 10_000)
    link.send(1, Edge.BLOCKED, 10_000)
    events = collect(link.trigger, 2)
    assert [(e.channel, round(e.t_s * 1e6)) for e in events] == [(0, 10_000), (1, 10_000)]


# --- Modbus -------------------------------------------------------------------------

def test_modbus_counter_jump_beyond_the_ring_is_missed_events():
    harness = ModbusHarness(ring_size=8)
    try:
        for i in range(11):
            harness.send(1, Edge.BLOCKED, 1000 + i)
        with pytest.raises(ProtocolError) as err:
            harness.trigger.events()
        assert ("missed 3 event(s): counter advanced by 11 since the last poll, "
                "the ring holds 8") in str(err.value)
        harness.send(1, Edge.CLEARED, 5000)  # resynchronised on the device's counter
        assert [round(e.t_s * 1e6) for e in collect(harness.trigger, 1)] == [5000]
    finally:
        harness.close()


def test_modbus_reads_a_full_ring_across_its_end_in_chunks():
    harness = ModbusHarness(ring_size=64)
    try:
        for i in range(20):  # move the write position near the ring's end
            harness.send(0, Edge.BLOCKED, i)
        assert len(collect(harness.trigger, 20)) == 20
        for i in range(64):  # exactly one ring, wrapping at slot 63 -> 0, > 31 per read
            harness.send(i % 4, Edge.CLEARED, 1000 + 10 * i)
        events = collect(harness.trigger, 64)
        assert [round(e.t_s * 1e6) for e in events] == [1000 + 10 * i for i in range(64)]
        assert [e.channel for e in events] == [i % 4 for i in range(64)]
    finally:
        harness.close()


def test_modbus_edges_before_connect_are_history():
    with ModbusCellServer() as server:
        server.record_edge(3, Edge.BLOCKED, 100)
        trigger = ModbusTrigger(port=server.port)
        assert trigger.events() == []
        server.record_edge(3, Edge.CLEARED, 200)
        assert [(e.edge, round(e.t_s * 1e6)) for e in collect(trigger, 1)] == [(Edge.CLEARED, 200)]
        trigger.close()


def test_modbus_unknown_edge_code_is_a_protocol_error():
    with ModbusCellServer() as server:
        trigger = ModbusTrigger(port=server.port)
        server.record_edge(5, Edge.BLOCKED, 100, edge_code=7)
        with pytest.raises(ProtocolError, match="event 0: unknown edge code 7"):
            trigger.events()
        trigger.close()


def test_modbus_trigger_connection_lost_is_a_device_error():
    server = ModbusCellServer().start()
    link_timeout_s = 0.5
    trigger = ModbusTrigger(port=server.port, timeout_s=link_timeout_s)
    server.stop()
    started = time.monotonic()
    with pytest.raises(DeviceError) as err:
        trigger.events(timeout_s=0.2)
    assert time.monotonic() - started < link_timeout_s + MARGIN_S  # the request's own deadline bounds it
    assert type(err.value) is DeviceError
    assert "lost while reading input register 100" in str(err.value)
    trigger.close()


# --- serial line ------------------------------------------------------------------------

def test_serial_bad_checksum_is_a_protocol_error(serial_link):
    serial_link.barrier.send_bytes(b"$TRG,0,1,B,1000*00\r\n")
    with pytest.raises(ProtocolError) as err:
        serial_link.trigger.events(timeout_s=WAIT_S)
    assert "bad checksum: sentence says 00, computed 03" in str(err.value)
    assert err.value.device == f"trigger (serial {serial_link.barrier.tty_path})"


def test_serial_truncated_sentence_is_refused_and_the_next_one_read(serial_link):
    serial_link.barrier.send_bytes(b"$TRG,0,1,B,10")  # cut off mid-sentence
    serial_link.send(1, Edge.CLEARED, 2000, seq=0)
    with pytest.raises(ProtocolError, match=r"truncated sentence \(next '\$' before end of line\)"):
        collect(serial_link.trigger, 1)
    events = collect(serial_link.trigger, 1)
    assert [(e.edge, round(e.t_s * 1e6)) for e in events] == [(Edge.CLEARED, 2000)]


def test_serial_malformed_field_is_a_protocol_error(serial_link):
    body = b"TRG,0,1,X,1000"
    checksum = 0
    for byte in body:
        checksum ^= byte
    serial_link.barrier.send_bytes(b"$" + body + b"*%02X\r\n" % checksum)
    with pytest.raises(ProtocolError, match="edge 'X', expected B or C"):
        serial_link.trigger.events(timeout_s=WAIT_S)


def test_serial_sequence_gap_counts_the_lost_sentences(serial_link):
    serial_link.send(0, Edge.BLOCKED, 100, seq=41)
    serial_link.send(0, Edge.CLEARED, 200, seq=44)
    with pytest.raises(ProtocolError, match=r"expected event 42, got 44 \(2 event\(s\) lost\)"):
        collect(serial_link.trigger, 2)


def test_serial_partial_sentence_at_open_is_skipped(serial_link):
    # pyserial flushes input at open; what comes first may still be a sentence's tail
    serial_link.barrier.send_bytes(b"G,9,1,B,77*4A\r\n")
    serial_link.send(4, Edge.BLOCKED, 500)
    assert [(e.channel, round(e.t_s * 1e6)) for e in collect(serial_link.trigger, 1)] == [(4, 500)]


def test_serial_line_hang_up_is_a_device_error(serial_link):
    serial_link.barrier.hang_up()
    with pytest.raises(DeviceError) as err:
        serial_link.trigger.events(timeout_s=WAIT_S)
    assert type(err.value) is DeviceError
    assert "serial line lost" in str(err.value)


def test_serial_missing_port_is_a_device_error_at_open():
    with pytest.raises(DeviceError) as err:
        SerialTrigger("/dev/cellcal-no-such-tty")
    assert type(err.value) is DeviceError
    assert "trigger (serial /dev/cellcal-no-such-tty): cannot open serial port" in str(err.value)


# --- CAN ------------------------------------------------------------------------------

def test_can_short_frame_is_a_protocol_error(can_link):
    can_link.barrier.send_data(b"\x00\x01\x01")
    with pytest.raises(ProtocolError, match="truncated frame: 3 data bytes, expected 8"):
        can_link.trigger.events(timeout_s=WAIT_S)


def test_can_overflow_status_bit_reports_lost_edges(can_link):
    can_link.send(1, Edge.BLOCKED, 100, status=0x01)
    with pytest.raises(ProtocolError, match=r"device reports lost edges \(queue overflow\)"):
        can_link.trigger.events(timeout_s=WAIT_S)


def test_can_frames_with_other_identifiers_are_not_ours(can_link):
    can_link.barrier.send_data(b"garbage!", arbitration_id=0x1A1)
    can_link.send(6, Edge.CLEARED, 700)
    assert [(e.channel, round(e.t_s * 1e6)) for e in collect(can_link.trigger, 1)] == [(6, 700)]


def test_can_sequence_gap_wraps_at_one_byte(can_link):
    can_link.send(0, Edge.BLOCKED, 100, seq=254)
    can_link.send(0, Edge.CLEARED, 200, seq=255)
    can_link.send(0, Edge.BLOCKED, 300, seq=0)  # 255 -> 0 is no gap
    assert len(collect(can_link.trigger, 3)) == 3
    can_link.send(0, Edge.CLEARED, 400, seq=2)
    with pytest.raises(ProtocolError, match=r"expected event 1, got 2 \(1 event\(s\) lost\)"):
        can_link.trigger.events(timeout_s=WAIT_S)


def test_can_missing_interface_is_a_device_error_at_open():
    with pytest.raises(DeviceError) as err:
        CanTrigger("cellcal-no-such-can", interface="socketcan")
    assert type(err.value) is DeviceError
    assert "cannot open CAN interface" in str(err.value)


def test_can_bus_going_away_is_a_device_error(can_link):
    can_link.trigger._bus.shutdown()  # as socketcan does when the interface goes down
    with pytest.raises(DeviceError, match="CAN bus lost") as err:
        can_link.trigger.events(timeout_s=0.1)
    assert not isinstance(err.value, (DeviceTimeout, ProtocolError))
