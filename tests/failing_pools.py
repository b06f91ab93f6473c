"""Worker pools that fail, shared by the test modules (a helper module: no tests here)."""

from concurrent.futures import Future


class LostWorkers:
    """An executor whose every worker dies (as one killed or out of memory would)."""

    def submit(self, *_, **__):
        future = Future()
        future.set_exception(RuntimeError("worker killed"))
        return future


class BrokenPool:
    """An executor whose pool broke while idle: submitting raises (as loky's does)."""

    def submit(self, *_, **__):
        raise RuntimeError("the pool is broken")
