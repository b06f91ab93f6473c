"""The live engine's patch policy, without fitting: which patches wait, which fits stand, which
are refitted (warm or polished), how results and failures are stored, which architecture the
later patches train."""

import dataclasses

import numpy as np
import pytest

import capture.live.patch_cache as patch_cache
from capture.live.patch_cache import FINAL_GROWTH, FitJob, FitResult, PatchCache, PatchFit
from capture.live.patches import READY_SHARE, LivePatches, PatchPoints
from capture.plan import ReconstructionParams

PARAMS = ReconstructionParams(voxel_mm=1.0, min_growth=0.1)


def cells(n: int) -> np.ndarray:
    """(n, 3) points, one per coverage cell (2 voxels = 2 mm): a coverage of exactly n."""
    return np.c_[2.0 * np.arange(n) + 0.5, np.full(n, 0.5), np.full(n, 0.5)]


@dataclasses.dataclass
class Model:
    hidden_layers_: tuple


def cache_with(name: str, coverage: int, polished: bool) -> tuple[PatchCache, Model]:
    cache, model = PatchCache(PARAMS), Model((4,))
    points = cells(coverage)
    cache.fits[name] = PatchFit(model, patch_cache._digest(points), coverage, polished)
    return cache, model


def test_a_first_fit_has_no_previous_and_is_polished_at_the_end_or_once_settled():
    cache = PatchCache(PARAMS)
    for final, settled, polish in ((False, False, False), (False, True, True), (True, False, True)):
        job = cache.job("a", cells(50), final=final, settled=settled)
        assert (job.name, job.previous, job.polish) == ("a", None, polish)
        np.testing.assert_array_equal(job.points, cells(50))
    assert cache.counts["reused"] == 0


@pytest.mark.parametrize("grown, final, settled, polished, refit", [
    (0, False, False, False, False),   # same points, between views: the fit stands
    (9, False, False, False, False),   # grew 9 % < min_growth 10 %: stands
    (10, False, False, False, True),   # grew 10 %: refit (warm, from the stored model)
    (9, False, True, False, True),     # settled: a polished fit is due
    (9, False, True, True, False),     # … and there is one
    (0, True, False, False, True),     # the end: only a polished fit stands …
    (0, True, False, True, False),     # … of the same points
    (2, True, False, True, False),     # grew 2 % < FINAL_GROWTH 3 %: stands
    (3, True, False, True, True),      # grew 3 %: polished again
])
def test_a_stored_fit_stands_or_is_refitted(grown, final, settled, polished, refit):
    assert PARAMS.min_growth == 0.1 and FINAL_GROWTH == 0.03
    cache, model = cache_with("a", 100, polished)
    job = cache.job("a", cells(100 + grown), final=final, settled=settled)
    if refit:
        assert job.previous is model and job.polish == (final or settled)
        assert cache.counts["reused"] == 0
    else:
        assert job is None and cache.counts["reused"] == 1


def test_run_stores_results_counts_failures_and_keeps_the_largest_searched_architecture(
        monkeypatch):
    outcomes = {"a": (Model((3,)), "fresh"), "b": (Model((5, 2)), "fresh"),
                "c": ValueError("too few points")}

    def fake_fit(points, previous, params, polish, layers):
        outcome = outcomes[fake_fit.names.pop(0)]
        assert layers is None  # the first fits search
        if isinstance(outcome, Exception):
            raise outcome
        return outcome

    fake_fit.names = ["a", "b", "c"]
    monkeypatch.setattr(patch_cache, "fit_patch", fake_fit)
    cache = PatchCache(PARAMS)
    jobs = [FitJob(n, cells(10 + i), None, polish=(n == "b")) for i, n in enumerate("abc")]
    assert cache.run(jobs) == ["c"]
    assert cache.counts == {"fresh": 2, "fixed": 0, "warm": 0, "reused": 0, "failed": 1}
    assert sorted(cache.fits) == ["a", "b"]
    assert cache.fits["a"].coverage == 10 and not cache.fits["a"].polished
    assert cache.fits["b"].coverage == 11 and cache.fits["b"].polished
    assert cache.layers == (5, 2)  # the most parameters of the searched nets


def test_failed_job_reports_its_error():
    result = patch_cache._fit_job(FitJob("x", np.eye(3), None, False), PARAMS, None)
    assert result.model is None and result.how == "failed"
    assert isinstance(result, FitResult) and result.error.split(":")[0].endswith("Error")


def present(**coverages) -> list[PatchPoints]:
    return [PatchPoints(name, cells(c), c, name == "cap") for name, c in coverages.items()]


def test_patches_wait_until_settled_and_big_enough_then_all_at_the_end():
    assert READY_SHARE == 0.6
    patches = LivePatches(PatchCache(PARAMS))
    # first update: nothing settled yet, nothing fitted
    assert patches.ready(present(s0=100, s1=50, s2=20, cap=10), final=False) == (set(), set())
    # s0 and s1 stopped growing; s1 is under 60 % of s0, s2 still grows; the cap need not be big
    ready, settled = patches.ready(present(s0=105, s1=52, s2=40, cap=10), final=False)
    assert settled == {"s0", "s1", "cap"} and ready == {"s0", "cap"}
    # s2 caught up with the largest sector (within min_growth): ready though it still grew
    ready, settled = patches.ready(present(s0=106, s1=53, s2=100, cap=10), final=False)
    assert ready == {"s0", "s2", "cap"} and "s2" not in settled
    # a patch fitted before stays ready
    patches.cache.fits["s1"] = PatchFit(Model((4,)), "", 53)
    ready, _ = patches.ready(present(s0=106, s1=80, s2=101, cap=10), final=False)
    assert "s1" in ready
    # at the end every patch with enough points is fitted
    ready, _ = patches.ready(present(s0=106, s1=200, s2=101, cap=30), final=True)
    assert ready == {"s0", "s1", "s2", "cap"}


class SerialExecutor:
    def submit(self, fn, *args):
        from concurrent.futures import Future

        future = Future()
        future.set_result(fn(*args))
        return future


def test_a_patch_fits_warnings_are_said_with_its_name(monkeypatch, caplog, recwarn):
    """A worker's fit's warnings (they went to its stderr, with a file and a line of code) come
    back with its result and are logged once, naming the patch."""
    import warnings

    from reconstruct.errors import ReconstructionWarning

    def fit_patch(points, previous, params, polish, layers):
        warnings.warn("boundary spline crosses itself", ReconstructionWarning, stacklevel=2)
        warnings.warn("boundary spline crosses itself", ReconstructionWarning, stacklevel=2)
        return Model((4,)), "fresh"

    monkeypatch.setattr(patch_cache, "fit_patch", fit_patch)
    cache = PatchCache(PARAMS)
    in_a_worker = SerialExecutor()  # the worker's function, here
    for _ in range(2):  # a refit saying it again: once
        assert cache.run([FitJob("sector 2", cells(12), None, False)], in_a_worker) == []
    said = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert said == ["patch sector 2: boundary spline crosses itself"]
    assert not [w for w in recwarn if issubclass(w.category, ReconstructionWarning)]
