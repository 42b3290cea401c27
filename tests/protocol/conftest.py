"""Fixtures of the protocol tests against the fake UR controller (test_ur_rtde_fake.py,
test_tool_frame_store.py): each fake in its own process on a loopback address of its own
(the controller's ports are fixed, so parallel tests cannot share one); every fake is
stopped and every adapter closed even when a test fails.

A fake runs on the suite's clock (SUITE_TIME_SCALE simulated seconds per wall second) unless a
test asks for another: what these tests check is stamped and bounded in the controller's time,
and the wall-time bounds they assert (a stale limit, a command's timeout) only get easier to meet
when the controller's clock runs ahead of the wall."""
import pytest

from support.daemon_harness import SUITE_TIME_SCALE


@pytest.fixture
def start_fake(loopback):
    """``fake = start_fake(**options)``: a FakeUrProcess started on a fresh loopback address,
    on the suite's clock unless ``time_scale`` says otherwise."""
    from cellcal.sims.fake_ur.process import FakeUrProcess

    fakes = []

    def start(**options):
        options.setdefault("time_scale", SUITE_TIME_SCALE)
        fake = FakeUrProcess(loopback(), **options)
        fakes.append(fake)
        return fake.start()

    yield start
    for fake in fakes:  # stop() ends the process even if it does not answer; fakes also exit with us
        fake.stop()


@pytest.fixture
def connect():
    """``device = connect(kind, *args, **options)``: a device (adapter, trigger) closed when the test ends."""
    opened = []

    def open_(kind, *args, **options):
        device = kind(*args, **options)
        opened.append(device)
        return device

    yield open_
    errors = []
    for device in reversed(opened):  # every device, even when one fails to close
        try:
            device.close()
        except Exception as exc:
            errors.append(exc)
    if errors:
        raise errors[0]


@pytest.fixture
def fake(start_fake):
    """One fake UR controller with its defaults."""
    return start_fake()
