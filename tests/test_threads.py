"""Training runs with its thread pools at one thread, whatever the shell sets."""

from threadpoolctl import threadpool_info

from reconstruct.networks import one_torch_thread
from reconstruct.threads import single_threaded


def test_training_runs_with_every_blas_pool_at_one_thread():
    import scipy.optimize  # noqa: F401  (its BLAS loaded, as in a fit)
    import torch

    with one_torch_thread():
        blas = [p for p in threadpool_info() if p["user_api"] == "blas"]
        assert blas and all(p["num_threads"] == 1 for p in blas)
        assert torch.get_num_threads() == 1
    with single_threaded():
        assert all(p["num_threads"] == 1 for p in threadpool_info())
