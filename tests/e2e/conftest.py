"""Fixtures of the end-to-end tests (the simulated cells, the daemon as a process)."""
import pytest


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
