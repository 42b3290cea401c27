"""Fixtures of the end-to-end tests (the simulated cells, the daemon as a process)."""
import pytest

from support.daemon_harness import SUITE_TIME_SCALE


@pytest.fixture(scope="session")
def sim_time_scale() -> float:
    """The end-to-end cases run the simulated cells' clock faster than the wall (tests/conftest.py)."""
    return SUITE_TIME_SCALE


@pytest.fixture(scope="module")
def net_cell():
    """The cell file a module's ``net`` serves, as ``cell_file(folder, host)`` for
    daemon_harness.Net (None: its short sim-net). A module that needs another cell defines
    a fixture of this name."""
    return None


@pytest.fixture(scope="module")
def net(net_cell, sim_time_scale, tmp_path_factory):
    """The networked simulated cell's fakes (daemon_harness.Net) on a loopback address of
    their own, on the suite's clock, running for the whole test module, reset once at the start (``cell_net``
    resets them again for a test). Stopped when the module ends."""
    from support.daemon_harness import Net

    net = Net(tmp_path_factory.mktemp("sim-net"), net_cell, sim_time_scale)
    try:
        net.reset()
        yield net
    finally:
        net.close()


@pytest.fixture
def cell_net(net):
    """The module's ``net`` reset for this test: the controller healthy, the arm at home with
    the previous frame, no fault pending."""
    net.reset()
    return net


@pytest.fixture
def cellcal_daemon(tmp_path):
    """``daemon = cellcal_daemon(net)``: ``cellcal daemon`` (a subprocess, ``python -m
    cellcal.cli.main daemon``) on a running daemon_harness.Net's cell, returned once it is
    ready, its state and log in `folder` (default the test's tmp_path; start it again on the
    same folder to restart it on the same store). Stopped when the test ends, if the test
    did not."""
    from support.daemon_harness import Daemon

    started = []

    def start(net, folder=None):
        started.append(Daemon(net, folder or tmp_path))
        return started[-1]

    yield start
    for daemon in started:
        daemon.stop()
