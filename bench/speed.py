"""Speed of the reconstruction engine on this machine, each against its peer in the same run.

    python -m bench.speed [--skip embedding training remesh endtoend] [--sizes 1600 20000 100000]
                          [--shapes sphere_cap s_curve torus_half]

1. Embedding: ours vs scikit-learn's Isomap (see bench/speed_embedding.py; ratio and Procrustes
   disparity against the S-curve's true parameters).
2. Adaptive search: our AdaptiveMLP (torch, L-BFGS, Net2Net growth) vs the same search (same
   split, same growth order and stopping rule) with scikit-learn's MLPRegressor (adam, early
   stopping); time and the fitted points' RMS distance to the true surface.
3. Re-mesh latency of a ~50k-vertex mesh through the saved ONNX map (median of repeats, λ
   alternating), against evaluating the same vertices through the torch network.
4. End to end (read → mesh) at each size on the sphere cap and on the two shapes the search
   takes longest on (the S-curve and the half torus; σ = 1 %), each in a fresh process, with its
   peak resident memory. Targets: 1,600 ≤ 10 s, 20,000 ≤ 30 s, 100,000 ≤ 120 s, ≤ 4 GB.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import resource
import statistics
import time
import warnings
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import trimesh  # noqa: E402

from bench.speed_embedding import print_table as print_embedding_table  # noqa: E402
from bench.speed_embedding import run_embedding_bench  # noqa: E402
from bench.speed_embedding import verdict as embedding_verdict  # noqa: E402
from reconstruct.embedding import SurfaceEmbedding  # noqa: E402
from reconstruct.meshing import default_spacing  # noqa: E402
from reconstruct.mlp import SPLIT, AdaptiveMLP  # noqa: E402
from reconstruct.pipeline import SurfaceReconstructor  # noqa: E402
from sim.shapes import make_shape  # noqa: E402

SEARCH = {"max_layers": 2, "max_neurons": 20}


def sklearn_search(uv, xyz, max_layers, max_neurons, neuron_patience=3, tol=0.005, seed=0):
    """The paper's growth with MLPRegressor: returns (hidden layers, predict function)."""
    from sklearn.exceptions import ConvergenceWarning
    from sklearn.neural_network import MLPRegressor

    rng = np.random.default_rng(seed)
    x_mean, x_scale = uv.mean(0), uv.std(0).max()
    y_mean, y_scale = xyz.mean(0), xyz.std(0)
    x, y = (uv - x_mean) / x_scale, (xyz - y_mean) / y_scale
    order = rng.permutation(len(x))
    n_train, n_test = int(round(SPLIT[0] * len(x))), int(round(SPLIT[1] * len(x)))
    train, test = order[:n_train], order[n_train : n_train + n_test]
    fit_rows = np.concatenate([train, order[n_train + n_test :]])  # train + validation
    best = None
    warnings.simplefilter("ignore", ConvergenceWarning)
    for _ in range(max_layers):
        layer_best, stale = None, 0
        for width in range(1, max_neurons + 1):
            layers = (*(best[1] if best else ()), width)
            net = MLPRegressor(
                hidden_layer_sizes=layers, activation="tanh", solver="adam", max_iter=300,
                early_stopping=True, validation_fraction=SPLIT[2] / (SPLIT[0] + SPLIT[2]),
                n_iter_no_change=10, random_state=seed,
            ).fit(x[fit_rows], y[fit_rows])
            score = 0.5 * np.mean((net.predict(x[train]) - y[train]) ** 2) + 0.5 * np.mean(
                (net.predict(x[test]) - y[test]) ** 2
            )
            if layer_best is None or score < layer_best[0] * (1 - tol):
                layer_best, stale = (score, layers, net), 0
            else:
                stale += 1
                if stale >= neuron_patience:
                    break
        if best is not None and layer_best[0] >= best[0] * (1 - tol):
            break
        if best is None or layer_best[0] < best[0]:
            best = layer_best
    net = best[2]
    return best[1], lambda q: net.predict((q - x_mean) / x_scale) * y_scale + y_mean


def training_bench(sizes=(1600, 20000), seed=0) -> list[dict]:
    rows = []
    for n in sizes:
        shape = make_shape("sphere_cap", n, noise=0.01, random_state=seed)
        embedding = SurfaceEmbedding(random_state=seed).fit(shape.points)
        uv, xyz = embedding.embedding_, shape.points[embedding.support_]
        truth = shape.truth
        started = time.perf_counter()
        ours = AdaptiveMLP(random_state=seed, **SEARCH).fit(uv, xyz)
        ours_s = time.perf_counter() - started
        started = time.perf_counter()
        layers, predict = sklearn_search(uv, xyz, seed=seed, **SEARCH)
        peer_s = time.perf_counter() - started

        def rms(p, truth=truth):  # RMS distance to the true surface
            _, distance, _ = trimesh.proximity.closest_point(truth, p)
            return float(np.sqrt(np.mean(distance**2)))

        rows.append({"n": n, "ours_s": ours_s, "ours_layers": ours.hidden_layers_,
                     "ours_rms": rms(ours.predict(uv)), "sk_s": peer_s, "sk_layers": layers,
                     "sk_rms": rms(predict(uv)), "input_rms": rms(xyz)})
        print(f"  training n={n} done", flush=True)
    return rows


def remesh_bench(seed=0, repeats=7) -> dict:
    shape = make_shape("sphere_cap", 20000, noise=0.01, random_state=seed)
    model = SurfaceReconstructor(random_state=seed).fit(shape.points)
    spacing = default_spacing(model.outline_, 50000)  # ~50k vertices inside the outline
    times, depth_times, vertices = [], [], 0
    for i in range(repeats):
        lam = (2.0, 3.0)[i % 2]
        started = time.perf_counter()
        mesh = model.remesh(lam=lam, grid_spacing=spacing)
        times.append(time.perf_counter() - started)
        vertices = len(mesh.vertices)
    for i in range(repeats):  # a new depth re-samples the boundary paths too (not cached)
        model.__dict__.pop("_boundary_cache", None)
        started = time.perf_counter()
        model.remesh(depth=(3, 2)[i % 2], grid_spacing=spacing)
        depth_times.append(time.perf_counter() - started)
    uv = model.vertices_2d_
    onnx_t, torch_t = [], []
    for _ in range(repeats):
        started = time.perf_counter()
        model.surface_map_(uv)
        onnx_t.append(time.perf_counter() - started)
        started = time.perf_counter()
        model.mlp_.predict_torch(uv)
        torch_t.append(time.perf_counter() - started)
    return {"vertices": vertices, "remesh_ms": 1000 * statistics.median(times),
            "depth_ms": 1000 * statistics.median(depth_times),
            "onnx_ms": 1000 * statistics.median(onnx_t),
            "torch_ms": 1000 * statistics.median(torch_t)}


def peak_memory_gb() -> float:
    """This process's peak resident memory. VmHWM restarts at exec, unlike ru_maxrss, which a
    spawned child inherits from its parent's fork."""
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 2**20  # kB → GiB
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def _end_to_end(name, n, seed, queue):
    """In a fresh process: the cloud as a PLY file → read → reconstruct → mesh file written."""
    import tempfile

    import torch

    from reconstruct.io import read_points, write_mesh

    torch.set_num_threads(1)
    warnings.simplefilter("ignore")
    shape = make_shape(name, n, noise=0.01, random_state=seed)
    with tempfile.TemporaryDirectory() as tmp:
        cloud, out = Path(tmp) / "cloud.ply", Path(tmp) / "mesh.ply"
        trimesh.PointCloud(shape.points).export(cloud)
        started = time.perf_counter()
        model = SurfaceReconstructor(random_state=seed).fit(read_points(cloud))
        write_mesh(model.mesh_, out)
        seconds = time.perf_counter() - started
    peak = peak_memory_gb()
    queue.put({"shape": name, "n": n, "seconds": seconds, "peak_gb": peak,
               "faces": len(model.mesh_.faces), "method": model.embedding_method_,
               "layers": model.hidden_layers_})


def end_to_end_bench(sizes, shapes, seed=0) -> list[dict]:
    rows = []
    context = multiprocessing.get_context("spawn")
    for n in sizes:
        for name in shapes:
            queue = context.Queue()
            process = context.Process(target=_end_to_end, args=(name, n, seed, queue))
            process.start()
            rows.append(queue.get())
            process.join()
            print(f"  end to end {name} n={n} done", flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--skip", nargs="*", default=[])
    parser.add_argument("--sizes", nargs="+", type=int, default=[1600, 20000, 100000])
    parser.add_argument("--shapes", nargs="+", default=["sphere_cap", "s_curve", "torus_half"])
    args = parser.parse_args()
    warnings.simplefilter("ignore")
    if "embedding" not in args.skip:
        rows = run_embedding_bench()
        print_embedding_table(rows)
        print(embedding_verdict(rows))
    if "training" not in args.skip:
        rows = training_bench()
        print("\nAdaptive search (sphere cap, σ = 1 %): ours vs scikit-learn MLPRegressor")
        print(f"{'N':>7}{'ours s':>9}{'layers':>10}{'rms':>9}{'sklearn s':>11}{'layers':>10}"
              f"{'rms':>9}{'ratio':>8}{'input rms':>11}")
        for r in rows:
            print(f"{r['n']:>7}{r['ours_s']:>9.2f}{str(r['ours_layers']):>10}{r['ours_rms']:>9.4f}"
                  f"{r['sk_s']:>11.2f}{str(r['sk_layers']):>10}{r['sk_rms']:>9.4f}"
                  f"{r['sk_s'] / r['ours_s']:>8.1f}{r['input_rms']:>11.4f}")
    if "remesh" not in args.skip:
        r = remesh_bench()
        print("\nRe-mesh without retraining (target ≤ 150 ms at 50k vertices; medians)")
        print(f"{'vertices':>9}{'new λ ms':>10}{'new depth ms':>14}{'onnx map ms':>13}"
              f"{'torch map ms':>14}")
        print(f"{r['vertices']:>9}{r['remesh_ms']:>10.1f}{r['depth_ms']:>14.1f}"
              f"{r['onnx_ms']:>13.1f}{r['torch_ms']:>14.1f}")
        met = max(r["remesh_ms"], r["depth_ms"]) <= 150
        print(f"target re-mesh ≤ 150 ms: {'met' if met else 'NOT met'}")
    if "endtoend" not in args.skip:
        rows = end_to_end_bench(args.sizes, args.shapes)
        targets = {1600: 10, 20000: 30, 100000: 120}
        print("\nEnd to end: PLY file read → mesh file written (σ = 1 %, fresh process each)")
        print(f"{'shape':<12}{'N':>7}{'seconds':>9}{'target':>8}{'peak GB':>9}{'faces':>8}"
              "  method / layers")
        missed = []
        for r in rows:
            target = targets.get(r["n"], float("nan"))
            print(f"{r['shape']:<12}{r['n']:>7}{r['seconds']:>9.2f}{target:>8.0f}"
                  f"{r['peak_gb']:>9.2f}{r['faces']:>8}  {r['method']} {r['layers']}")
            if r["seconds"] > target or r["peak_gb"] > 4.0:
                missed.append(f"{r['shape']} {r['n']}")
        print("targets (time above, memory ≤ 4 GB): " + (
            "met" if not missed else "NOT met: " + ", ".join(missed)))


if __name__ == "__main__":
    main()
