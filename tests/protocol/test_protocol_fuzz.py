"""Random bytes and lines into the serial-trigger and tracker parsers: only ProtocolError
(or a well-formed result) comes out, and every example finishes in bounded time."""
import time
from datetime import timedelta

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cellcal.drivers.triggers.can_bus import parse_trigger_frame
from cellcal.drivers.interfaces import DeviceError, Edge, ProtocolError, TrackerMeasurement
from cellcal.drivers.triggers.serial_line import (SentenceFramer, SerialTrigger, format_trigger_sentence,
                                            parse_trigger_sentence)
from cellcal.drivers.triggers.stream import TriggerRecord, TriggerSequencer
from cellcal.drivers.tracker_socket import (TrackerReply, TrackerSocket, parse_reply,
                                            with_checksum)
from cellcal.sims.net.serial_barrier import SerialBarrier
from cellcal.sims.net.tracker_server import TrackerServer

DEVICE = "fuzzed device"
MARGIN_S = 2.0  # scheduling slack on top of a deadline: a 2-core machine with both cores busy wakes a waiter late
# a parse of a few hundred bytes that takes seconds has gone pathological (backtracking), not slow
PURE = settings(max_examples=200, deadline=timedelta(seconds=MARGIN_S))
# no per-example deadline: each test over I/O asserts the deadline its driver promises
OVER_IO = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])

records = st.builds(TriggerRecord, seq=st.integers(0, 65535), channel=st.integers(0, 255),
                    edge=st.sampled_from(list(Edge)), t_us=st.integers(0, 2**32 - 1))
# the protocol's own alphabet, so that many examples get past the first checks
sentence_text = st.text(alphabet="$TRG,BC*0123456789ABCDEF\r\n -", max_size=90)
reply_tokens = st.lists(st.one_of(
    st.sampled_from(["OK", "ERR", "ok", "-", "1", "nan", "inf", "1e999", "1_0", "0.5", "-0.5"]),
    st.from_regex(r"[-+]?[0-9]{0,4}\.?[0-9]{0,4}([eE][-+]?[0-9]{1,3})?", fullmatch=True),
    st.text(max_size=6)), max_size=14)


# --- serial trigger -------------------------------------------------------------------

@PURE
@given(st.binary(max_size=120))
def test_random_bytes_never_parse_to_anything_but_a_record_or_protocol_error(line):
    try:
        record = parse_trigger_sentence(line, DEVICE)
    except ProtocolError as exc:
        assert exc.device == DEVICE
        return
    assert record is None or isinstance(record, TriggerRecord)


@PURE
@given(sentence_text)
def test_protocol_alphabet_lines_never_escape_as_other_errors(text):
    try:
        parse_trigger_sentence(text.encode(), DEVICE)
    except ProtocolError:
        pass


@PURE
@given(records, st.data())
def test_any_single_byte_corruption_is_refused_or_harmless(record, data):
    sentence = format_trigger_sentence(record.seq, record.channel, record.edge, record.t_us)
    line = bytearray(sentence.removesuffix(b"\r\n"))
    index = data.draw(st.integers(0, len(line) - 1))
    line[index] = data.draw(st.integers(0, 255).filter(lambda b: b != line[index]))
    try:
        parsed = parse_trigger_sentence(bytes(line), DEVICE)
    except ProtocolError:
        return
    # only a change of checksum hex case (a -> A) may get through, and changes nothing
    assert parsed == record


@PURE
@given(st.lists(records, max_size=12), st.lists(st.integers(1, 40), min_size=1))
def test_sentences_split_anywhere_come_out_whole(sent, chunk_sizes):
    stream = b"".join(format_trigger_sentence(r.seq, r.channel, r.edge, r.t_us) for r in sent)
    framer = SentenceFramer(DEVICE)
    received, position, k = [], 0, 0
    while position < len(stream):
        size = chunk_sizes[k % len(chunk_sizes)]
        framer.feed(stream[position:position + size])
        position, k = position + size, k + 1
        while (line := framer.next_line()) is not None:
            received.append(parse_trigger_sentence(line, DEVICE))
    assert received == sent


@PURE
@given(st.lists(st.binary(max_size=50), max_size=20))
def test_framer_on_noise_raises_only_protocol_errors_and_stays_bounded(chunks):
    framer = SentenceFramer(DEVICE)
    for chunk in chunks:
        framer.feed(chunk)
        for _ in range(200):  # each call consumes input or returns None: never spins
            try:
                if framer.next_line() is None:
                    break
            except ProtocolError:
                continue
        else:
            pytest.fail("framer did not come to rest on its input")
        assert len(framer._buffer) <= 82 + 50


@PURE
@given(st.lists(records, max_size=30))
def test_sequencer_on_random_records_raises_only_protocol_errors(stream):
    sequencer = TriggerSequencer(DEVICE, 65536)
    for record in stream:
        try:
            event = sequencer.accept(record)
        except ProtocolError:
            continue
        assert event.t_s >= 0 and event.channel == record.channel


@PURE
@given(st.binary(max_size=16))
def test_random_can_payloads_parse_or_raise_protocol_error(data):
    try:
        record = parse_trigger_frame(data, DEVICE)
    except ProtocolError:
        return
    assert len(data) == 8 and isinstance(record, TriggerRecord)


@OVER_IO
@given(st.lists(st.binary(min_size=1, max_size=60), max_size=6))
def test_serial_trigger_on_a_noisy_line_raises_only_protocol_errors(noise):
    with SerialBarrier() as barrier:
        trigger = SerialTrigger(barrier.tty_path)
        try:
            for chunk in noise:
                barrier.send_bytes(chunk)
            poll_s, quiet_after_s = 0.01, 0.05
            started = time.monotonic()
            for _ in range(len(noise) * 60 + 5):
                try:
                    if not trigger.events(timeout_s=poll_s) and time.monotonic() - started > quiet_after_s:
                        break
                except ProtocolError:
                    continue
            # it ends at the first empty poll past quiet_after_s, and no poll waits beyond its poll_s
            assert time.monotonic() - started < quiet_after_s + poll_s + MARGIN_S
        finally:
            trigger.close()


# --- tracker ----------------------------------------------------------------------------

@PURE
@given(st.binary(max_size=200))
def test_random_reply_bytes_parse_or_raise_protocol_error(line):
    try:
        reply = parse_reply(line, DEVICE)
    except ProtocolError:
        return
    assert isinstance(reply, TrackerReply)


@PURE
@given(reply_tokens)
def test_checksummed_token_soup_parses_or_raises_protocol_error(tokens):
    try:
        body = " ".join(tokens)
        line = with_checksum(body).removesuffix(b"\r\n")
    except UnicodeEncodeError:
        line = " ".join(tokens).encode("utf-8") + b"*00"
    try:
        reply = parse_reply(line, DEVICE)
    except ProtocolError:
        return
    if reply.measurement is not None:
        assert np.all(np.isfinite(reply.measurement.position_m))
        assert reply.measurement.quality >= 0


@PURE
@given(st.integers(0, 999_999_999), st.floats(0, 1e6), st.lists(
    st.floats(-100, 100, allow_nan=False), min_size=3, max_size=3), st.floats(0, 1e-2))
def test_well_formed_ok_replies_round_trip(seq, t_s, xyz, sigma_m):
    line = with_checksum(f"OK {seq} ok {t_s:.6f} {' '.join(f'{v:.7f}' for v in xyz)} "
                         f"{sigma_m:.3e}").removesuffix(b"\r\n")
    reply = parse_reply(line, DEVICE)
    assert reply.seq == seq
    assert np.allclose(reply.measurement.position_m, xyz, atol=1e-7)


@pytest.fixture(scope="module")
def fuzz_tracker_server():
    with TrackerServer(lambda target: np.array([1.0, 2.0, 3.0])) as server:
        yield server


@OVER_IO
@given(st.binary(max_size=300))
def test_tracker_client_on_random_replies_fails_only_with_device_errors(fuzz_tracker_server,
                                                                          raw):
    tracker, timeout_s = TrackerSocket(port=fuzz_tracker_server.port), 0.1
    fuzz_tracker_server.inject_reply(raw + b"\n")
    started = time.monotonic()
    try:
        result = tracker.measure("smr1", timeout_s=timeout_s)
        assert isinstance(result, TrackerMeasurement)
    except DeviceError:  # ProtocolError, DeviceTimeout or TrackerStatusError
        pass
    finally:
        tracker.close()
    assert time.monotonic() - started < timeout_s + MARGIN_S  # measure's timeout bounds it, a reconnect included
