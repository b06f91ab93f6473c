import os

# Two shared cores: keep numeric libraries single-threaded so tests are stable.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import logging  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402

import pytest  # noqa: E402
from scan_helpers import FAST_PARAMS  # noqa: E402

from capture import LOGGERS  # noqa: E402
from capture.plan import ReconstructionParams  # noqa: E402

# Dask's client threads may log after a test ends, into a stream pytest's capture has closed:
# under xdist each such record printed a "--- Logging error ---" traceback into the log.
logging.raiseExceptions = False


def pytest_addoption(parser):
    parser.addoption("--runslow", action="store_true", help="also run tests marked slow")


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_auto_num_workers(config) -> int:
    """``-n auto`` (`.ci/run`): one worker per core this process may use, at most 4 (a worker
    holds about 1.2 GB, and tests start processes of their own)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return max(1, min(4, cores or 1))


def pytest_collection_modifyitems(config, items):
    if config.getoption("--runslow"):
        return
    skip = pytest.mark.skip(reason="slow: run with --runslow")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)


@pytest.fixture(scope="session")
def fast_params() -> ReconstructionParams:
    """Tiny networks and coarse voxels: the engine's logic, not the paper's accuracy, on test."""
    return FAST_PARAMS


#: Our own worker threads are daemon threads (an interpreter may exit under a running scan), so
#: they are checked by name: the scan runner, the engine, the daemon's reader.
OWN_DAEMON_THREADS = ("scan-",)


def _leaked(before) -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t not in before and t.is_alive()
            and (not t.daemon or t.name.startswith(OWN_DAEMON_THREADS))]


@pytest.fixture(autouse=True)
def no_leaked_threads():
    """Every device, runner and engine closes its threads: a test that leaks one fails."""
    before = set(threading.enumerate())
    yield
    deadline = time.monotonic() + 2.0
    while (leaked := _leaked(before)) and time.monotonic() < deadline:
        time.sleep(0.02)
    if leaked:
        pytest.fail(f"test leaked threads: {', '.join(t.name for t in leaked)}")


@pytest.fixture(autouse=True)
def cli_output_restored():
    """A test that runs the CLI leaves the logging and warnings as it found them: its INFO
    level on ``reconstruct`` made a later test's caplog hold every fit's progress lines."""
    import warnings

    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    levels = {name: logging.getLogger(name).level for name in LOGGERS}
    showwarning = warnings.showwarning
    yield
    for handler in root.handlers[:]:  # the CLI's own (pytest adds and drops its per phase)
        if handler not in handlers and not type(handler).__module__.startswith("_pytest"):
            root.removeHandler(handler)
    root.setLevel(level)
    for name, kept in levels.items():
        logging.getLogger(name).setLevel(kept)
    warnings.showwarning = showwarning


@pytest.fixture
def leaked_threads():
    """The leak check itself: ``leaked_threads(before)`` lists the threads it would fail on."""
    return _leaked


@pytest.fixture
def state_dir(tmp_path):
    """A daemon's state dir, not created yet (the daemon makes it, 0700)."""
    return tmp_path / "state"


@pytest.fixture
def client(state_dir):
    """The daemon's app on ``state_dir``, in this process (`fastapi.testclient.TestClient`)."""
    from fastapi.testclient import TestClient

    from capture.daemon.app import create_app

    with TestClient(create_app(state_dir)) as client:
        yield client
