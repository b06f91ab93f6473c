"""Embedding speed and quality: our SurfaceEmbedding vs scikit-learn's Isomap, same run.

    python -m bench.speed_embedding [--sizes 1600 5000 10000] [--big 20000 100000]

Data: the S-curve (sim.shapes, noise σ = 0.5 % of the diagonal), whose true parameters (t, h)
are arc-length coordinates, so a good embedding matches them up to a rigid motion. Quality is
the Procrustes disparity against them (scipy.spatial.procrustes; 0 is perfect). Ours runs with
the automatic method and K (its time includes choosing K); scikit-learn's Isomap gets the same K
and the same points. Times are medians of repeats where a run is cheap. The big sizes run ours
alone, each in a fresh process, and report its peak resident memory.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import statistics
import time
import warnings

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from scipy.spatial import procrustes  # noqa: E402
from sklearn.manifold import Isomap  # noqa: E402

from reconstruct.embedding import SurfaceEmbedding  # noqa: E402
from sim.shapes import make_shape  # noqa: E402

NOISE = 0.005
CHEAP_SECONDS = 5.0
REPEATS = 3


def _timed(function, repeats: int):
    """(median seconds, last result); repeats only while a run is cheap."""
    times, result = [], None
    for _ in range(repeats):
        started = time.perf_counter()
        result = function()
        times.append(time.perf_counter() - started)
        if times[-1] > CHEAP_SECONDS:
            break
    return statistics.median(times), result


def compare_with_sklearn(n_points: int, seed: int = 0) -> dict:
    """One size: ours (auto) vs sklearn Isomap with our K, on the points we kept."""
    shape = make_shape("s_curve", n_points, noise=NOISE, random_state=seed)
    ours_seconds, ours = _timed(
        lambda: SurfaceEmbedding(random_state=seed).fit(shape.points), REPEATS
    )
    points, params = shape.points[ours.support_], shape.params[ours.support_]
    fixed_seconds, _ = _timed(
        lambda: SurfaceEmbedding(
            method=ours.method_, n_neighbors=ours.n_neighbors_, random_state=seed
        ).fit(shape.points),
        REPEATS,
    )
    peer = Isomap(n_neighbors=ours.n_neighbors_, n_components=2)
    peer_seconds, peer_embedding = _timed(lambda: peer.fit_transform(points), REPEATS)
    return {
        "n": n_points,
        "method": ours.method_,
        "K": ours.n_neighbors_,
        "ours_s": ours_seconds,
        "ours_fixed_k_s": fixed_seconds,
        "sklearn_s": peer_seconds,
        "speedup": peer_seconds / ours_seconds,
        "ours_disparity": procrustes(params, ours.embedding_)[2],
        "sklearn_disparity": procrustes(params, peer_embedding)[2],
    }


def _ours_alone(n_points: int, seed: int, queue) -> None:
    shape = make_shape("s_curve", n_points, noise=NOISE, random_state=seed)
    started = time.perf_counter()
    model = SurfaceEmbedding(random_state=seed).fit(shape.points)
    seconds = time.perf_counter() - started
    from bench.speed import peak_memory_gb

    peak_gb = peak_memory_gb()
    disparity = procrustes(shape.params[model.support_], model.embedding_)[2]
    queue.put(
        {
            "n": n_points,
            "method": model.method_,
            "K": model.n_neighbors_,
            "ours_s": seconds,
            "ours_disparity": disparity,
            "peak_rss_gb": peak_gb,
        }
    )


def ours_alone(n_points: int, seed: int = 0) -> dict:
    """One big size, ours only, in a fresh process (so its peak memory is its own)."""
    context = multiprocessing.get_context("fork")
    queue = context.Queue()
    process = context.Process(target=_ours_alone, args=(n_points, seed, queue))
    process.start()
    row = queue.get()
    process.join()
    return row


def run_embedding_bench(sizes=(1600, 5000, 10000), big=(20000, 100000)) -> list[dict]:
    """All rows: ``sizes`` against sklearn, ``big`` ours alone."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return [compare_with_sklearn(n) for n in sizes] + [ours_alone(n) for n in big]


def print_table(rows: list[dict]) -> None:
    def cell(row, key, spec):
        return format(row[key], spec) if key in row else "—"

    header = (
        f"{'N':>7} {'method':<9}{'K':>3} {'ours s':>8} {'fixed-K s':>10} {'sklearn s':>10}"
        f" {'speedup':>8} {'disp ours':>10} {'disp sklearn':>13} {'peak GB':>8}"
    )
    print(header)
    print("-" * len(header))
    for row in rows:
        print(
            f"{row['n']:>7} {row['method']:<9}{row['K']:>3} {cell(row, 'ours_s', '.2f'):>8}"
            f" {cell(row, 'ours_fixed_k_s', '.2f'):>10} {cell(row, 'sklearn_s', '.2f'):>10}"
            f" {cell(row, 'speedup', '.1f'):>8} {cell(row, 'ours_disparity', '.2e'):>10}"
            f" {cell(row, 'sklearn_disparity', '.2e'):>13} {cell(row, 'peak_rss_gb', '.2f'):>8}"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="*", type=int, default=[1600, 5000, 10000])
    parser.add_argument("--big", nargs="*", type=int, default=[20000, 100000])
    args = parser.parse_args()
    rows = run_embedding_bench(tuple(args.sizes), tuple(args.big))
    print_table(rows)
    print(verdict(rows))


def verdict(rows) -> str:
    """The target line: at 10k, >= 10x faster than scikit-learn at equal quality."""
    at_10k = [r for r in rows if r["n"] == 10000 and "sklearn_s" in r]
    if not at_10k:
        return "target at 10k: not measured (no 10000 in --sizes)"
    r = at_10k[0]
    met = r["speedup"] >= 10 and r["ours_disparity"] <= 1.05 * r["sklearn_disparity"]
    return (f"target at 10k (>= 10x faster, Procrustes disparity equal or better, 5 % "
            f"tolerance): {'met' if met else 'NOT met'}")


if __name__ == "__main__":
    main()
