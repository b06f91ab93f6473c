"""Thread pools sized by the program (reconstruct/threads.py), whatever the shell sets."""

import os
import subprocess
import sys

from threadpoolctl import threadpool_info

from reconstruct.networks import one_torch_thread
from reconstruct.threads import available_cores, single_threaded


def test_training_runs_with_every_blas_pool_at_one_thread():
    import scipy.optimize  # noqa: F401  (its BLAS loaded, as in a fit)

    with one_torch_thread():
        blas = [p for p in threadpool_info() if p["user_api"] == "blas"]
        assert blas and all(p["num_threads"] == 1 for p in blas)
    with single_threaded():
        assert all(p["num_threads"] == 1 for p in threadpool_info())


def test_a_worker_limits_its_pools_to_its_share_of_the_cores():
    """In a plain environment (no thread variables), `limit_threads(2)` leaves each of two
    processes half the cores, torch included."""
    code = (
        "from reconstruct.threads import limit_threads\n"
        "import numpy, torch\n"
        "from threadpoolctl import threadpool_info\n"
        "n = limit_threads(2)\n"
        "print(n, torch.get_num_threads(), "
        "max(p['num_threads'] for p in threadpool_info() if p['user_api'] == 'blas'))"
    )
    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, env=env)
    share = max(1, available_cores() // 2)
    assert out.stdout.split() == [str(share)] * 3
