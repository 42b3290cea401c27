import pytest
from threadpoolctl import threadpool_limits


@pytest.fixture(autouse=True, scope="session")
def single_threaded_blas():
    """As the command line runs: small dense problems are slower with BLAS threads."""
    with threadpool_limits(limits=1, user_api="blas"):
        yield
