import os

# Two shared cores: keep numeric libraries single-threaded so tests are stable.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import threading  # noqa: E402

import pytest  # noqa: E402


def pytest_addoption(parser):
    parser.addoption("--runslow", action="store_true", help="also run tests marked slow")


def pytest_collection_modifyitems(config, items):
    if config.getoption("--runslow"):
        return
    skip = pytest.mark.skip(reason="slow: run with --runslow")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)


@pytest.fixture(autouse=True)
def no_leaked_threads():
    """Every device closes its threads: a test that leaks one fails."""
    before = set(threading.enumerate())
    yield
    deadline = 2.0
    import time

    t0 = time.monotonic()
    while time.monotonic() - t0 < deadline:
        leaked = [
            t for t in threading.enumerate() if t not in before and t.is_alive() and not t.daemon
        ]
        if not leaked:
            return
        time.sleep(0.02)
    names = ", ".join(t.name for t in leaked)
    pytest.fail(f"test leaked threads: {names}")
