"""Fixtures every kind of test shares (tests/unit, tests/protocol, tests/e2e).

The helpers are plain modules of tests/support/ (tests/ is on sys.path through this
conftest): hidden_cases (generated data with a hidden effect), report_check (a report's
drawings), naming_stubs (made-up scores for the naming rule), routine_checks (a robot that
records its commands, and a check of each against the cell's limits), cell_edits (a cell
file changed through its YAML), loopback (addresses of a test's own), daemon_harness
(``cellcal daemon`` on the networked simulated cell), service_panel (the service pressed from
its panel). The benches in bench/ use some of them.
"""
import pytest
from threadpoolctl import threadpool_limits

from support import loopback as _loopback

# The files whose cases wait longest on the simulated arm, longest first, in the collection's order.
# Note: `make test`'s `--dist loadfile` hands files to its two workers by how many cases each holds
# (pytest-xdist's --loadscope-reorder, on by default), not in this order; measured, its two workers end
# within a few seconds of each other all the same, and --no-loadscope-reorder was no faster. The order
# here decides a run without that reordering (one process, or --no-loadscope-reorder).
LONGEST_FIRST = ("e2e/test_time_scale.py", "e2e/test_tracker_routine.py", "e2e/test_daemon_e2e.py",
                 "e2e/test_tool_change_panel.py", "e2e/test_tcp_laser.py", "e2e/test_sim_cells.py",
                 "e2e/test_handshake.py", "e2e/test_tcp_check_panel.py", "e2e/test_tcp_stylus.py",
                 # the longest of those `make test-fast` runs
                 "protocol/test_ur_rtde_fake.py", "unit/test_routine_framework.py")


def pytest_collection_modifyitems(config, items):
    def rank(item) -> int:
        path = item.nodeid.split("::")[0].removeprefix("tests/")
        return LONGEST_FIRST.index(path) if path in LONGEST_FIRST else len(LONGEST_FIRST)

    items.sort(key=rank)  # stable: every other file, and the cases within a file, keep their order


@pytest.fixture(autouse=True, scope="session")
def single_threaded_blas():
    """As the command line runs: small dense problems are slower with BLAS threads."""
    with threadpool_limits(limits=1, user_api="blas"):
        yield


@pytest.fixture
def loopback():
    """``host = loopback()``: a loopback address no other test holds (in this run, its other
    xdist worker or another run on the machine), for fakes on fixed ports; each call gives
    another. All are given back when the test ends."""
    hosts = []

    def allocate() -> str:
        hosts.append(_loopback.allocate())
        return hosts[-1]

    yield allocate
    for host in hosts:
        _loopback.release(host)


@pytest.fixture
def loopback_host(loopback) -> str:
    """One loopback address of the test's own (see ``loopback``)."""
    return loopback()


@pytest.fixture(scope="session")
def sim_time_scale() -> float:
    """The simulated cells' clock, in simulated seconds per wall second (tests/e2e runs faster)."""
    return 1.0


@pytest.fixture
def start_sim_net(loopback, sim_time_scale):
    """``cell, sim = start_sim_net(cell, time_scale=None)``: the fakes of a networked cell (a loaded
    cell or a shipped cell's name; default sim-net) on a loopback address of their own, in process
    (SimCell: the fake UR controller in its own process, the Modbus IO module and the
    tracker server in threads), on a clock `time_scale` times the wall's (default
    ``sim_time_scale``); the cell returned points there. Stopped when the test ends."""
    from cellcal.daemon.cells import load_cell
    from cellcal.sims.net.cell import SimCell

    running = []

    def start(cell="sim-net", time_scale=None):
        cell = (load_cell(cell) if isinstance(cell, str) else cell).on_host(loopback())
        running.append(SimCell(cell, time_scale=sim_time_scale if time_scale is None else time_scale).start())
        return cell, running[-1]

    yield start
    for sim in reversed(running):
        sim.stop()


@pytest.fixture(scope="module")
def sim_net(sim_time_scale):
    """The shipped sim-net cell's fakes on a loopback address of their own, running for the
    whole test module: ``cell, sim = sim_net`` (the cell pointing at them)."""
    from cellcal.daemon.cells import load_cell
    from cellcal.sims.net.cell import SimCell

    with _loopback.held() as host:
        cell = load_cell("sim-net").on_host(host)
        with SimCell(cell, time_scale=sim_time_scale) as sim:
            yield cell, sim
