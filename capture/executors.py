"""Where fits run: local processes by default, or a Dask cluster chosen with ``--cluster``.

`make_executor` returns a `concurrent.futures.Executor`. Without a cluster it is a spawn
`ProcessPoolExecutor` of ``workers`` processes (None with ``workers`` <= 1: run inline). With
``cluster="tcp://host:8786"`` it is a `distributed.Client`'s executor on that scheduler; Dask
is imported only then (the ``cluster`` extra), so the default path never loads it. Tasks are
plain functions with picklable arguments (points and parameters out, the fitted
`SurfaceReconstructor` — ONNX bytes and its state — back). A worker lost mid-task is retried
by Dask on another worker (``distributed.scheduler.allowed-failures``, 3 by default).
"""

from __future__ import annotations

import concurrent.futures
import logging
import multiprocessing

log = logging.getLogger(__name__)

#: Seconds to reach the scheduler before giving up with a one-line error.
CONNECT_TIMEOUT_S = 10.0


class ClusterError(ConnectionError):
    """The Dask cluster cannot be used (unreachable scheduler, no workers, Dask not installed)."""


def make_executor(cluster: str | None = None, workers: int = 1, warm_up: bool = True,
                  timeout: float | None = None):
    """A `concurrent.futures.Executor` for fits, or None (inline) without a cluster and with
    ``workers`` <= 1. The caller shuts it down. ``warm_up``: import the fitting stack (torch,
    onnxruntime) in every worker now, while the caller does something else.  timeout : seconds
    to reach the scheduler (default `CONNECT_TIMEOUT_S`)."""
    if cluster:
        return ClusterExecutor(cluster, timeout=timeout, warm_up=warm_up)
    if workers <= 1:
        return None
    executor = concurrent.futures.ProcessPoolExecutor(
        workers, mp_context=multiprocessing.get_context("spawn"))
    if warm_up:
        for _ in range(workers):
            executor.submit(warm_up_worker)
    return executor


class ClusterExecutor(concurrent.futures.Executor):
    """A Dask cluster behind the `concurrent.futures` interface; owns its `distributed.Client`.

    address : the scheduler, e.g. ``tcp://10.0.0.5:8786`` or ``tls://…`` (TLS settings from
    Dask's configuration, ``distributed.comm.tls.*``).
    Attributes: ``client`` (`distributed.Client`), ``address``, ``n_workers`` (at connection).
    """

    def __init__(self, address: str, timeout: float | None = None, warm_up: bool = True):
        try:
            import distributed
        except ImportError as exc:
            raise ClusterError("--cluster needs Dask: pip install 'scanstation[cluster]' "
                               f"({exc})") from exc
        self.address = address
        timeout = CONNECT_TIMEOUT_S if timeout is None else timeout
        _check_host(address)
        try:
            self.client = distributed.Client(address, timeout=f"{timeout}s",
                                             set_as_default=False)
        except (OSError, TimeoutError, ValueError) as exc:
            raise ClusterError(f"Dask scheduler {address} unreachable: "
                               f"{_one_line(exc)}") from exc
        try:
            workers = self.client.scheduler_info().get("workers", {})
            self.n_workers = len(workers)
            if self.n_workers == 0:
                log.warning("Dask scheduler %s has no workers yet: fits wait for one", address)
            else:
                log.info("Dask cluster %s: %d workers", address, self.n_workers)
            if warm_up:
                for worker in workers:
                    distributed.fire_and_forget(self.client.submit(
                        warm_up_worker, workers=[worker], allow_other_workers=False,
                        pure=False))
            self._executor = self.client.get_executor(pure=False)
        except BaseException:
            self.client.close()
            raise

    def submit(self, fn, /, *args, **kwargs) -> concurrent.futures.Future:
        return self._executor.submit(fn, *args, **kwargs)

    def map(self, fn, *iterables, timeout=None, chunksize=1):
        return self._executor.map(fn, *iterables, timeout=timeout)

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        """Cancel what is left (``cancel_futures``) or wait for it, then close the client (the
        cluster keeps running for the other stations)."""
        if self.client.status == "closed":
            return
        try:
            self._executor.shutdown(wait=wait and not cancel_futures)  # wait=False cancels
        finally:
            self.client.close()


def warm_up_worker() -> None:
    """Import the fitting stack (torch, onnxruntime) in this worker, single-threaded."""
    import reconstruct.networks
    import reconstruct.pipeline  # noqa: F401  (and torch, onnxruntime)

    reconstruct.networks.load_torch()


def _check_host(address: str) -> None:
    """Fail at once on a host name that does not resolve (Dask would retry until its timeout)."""
    import socket
    import urllib.parse

    parts = urllib.parse.urlsplit(address if "://" in address else f"tcp://{address}")
    if parts.scheme in ("tcp", "tls") and parts.hostname:
        try:
            socket.getaddrinfo(parts.hostname, None)
        except OSError as exc:
            raise ClusterError(f"Dask scheduler {address} unreachable: cannot resolve "
                               f"{parts.hostname} ({exc.strerror or exc})") from exc


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__
