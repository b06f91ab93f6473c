"""`scanstation reprocess RECORDING|DIR… [--cluster ADDRESS] [-o OUT]`: many replays at once.

One task per recording on local processes (``--workers``) or a Dask cluster (``--cluster``);
a progress bar over recordings on stderr, a summary table on stdout, exit 1 if any failed.
"""

from __future__ import annotations

import logging
import os
import sys

log = logging.getLogger("capture.cli")


def add_parser(subparsers) -> None:
    from .scan import add_cluster_option, workers_count

    parser = subparsers.add_parser(
        "reprocess", help="rebuild mesh, cloud and report of many recordings (resumable; local "
        "processes or a Dask cluster)",
        description="Re-run the reconstruction of each recording (its recorded plan, "
        "calibration and update schedule) into OUT/NAME/: mesh.ply, cloud.ply, scan.json, "
        "engine/. A recording whose outputs are up to date for the same inputs and parameters "
        "is skipped; a failing recording does not stop the others.")
    parser.add_argument("recordings", nargs="+", metavar="RECORDING|DIR",
                        help="recording .mcap files, scan folders, or folders holding them")
    parser.add_argument("-o", "--output", default="out/reprocess", metavar="OUT",
                        help="output folder (default: out/reprocess)")
    parser.add_argument("--lam", type=float, default=None, help="spline smoothing λ")
    parser.add_argument("--depth", type=int, default=None, help="boundary path depths")
    parser.add_argument("--seed", type=int, default=None, help="random seed (same seed, same "
                        "mesh)")
    add_cluster_option(parser)
    parser.add_argument("--workers", type=workers_count, default=os.cpu_count() or 1,
                        help="local processes without --cluster (default: one per core)")
    parser.add_argument("--force", action="store_true", help="redo up-to-date recordings too")
    parser.set_defaults(run=run)


def run(args) -> int:
    import time

    from capture.executors import make_executor
    from capture.reprocess import Reprocessor, find_recordings

    from .scan import engine_overrides

    jobs = find_recordings(args.recordings)
    log.info("%d recordings to %s", len(jobs), args.output)
    bar = ProgressBar(len(jobs), enabled=logging.getLogger("capture").level <= logging.INFO)
    executor = make_executor(args.cluster, min(args.workers, len(jobs)))
    started = time.perf_counter()
    try:
        outcomes = Reprocessor(args.output, engine_overrides(args), executor, force=args.force,
                               on_outcome=bar.update).run(jobs)
    finally:
        bar.close()
        if executor is not None:
            executor.shutdown(wait=False, cancel_futures=True)
    print_summary(outcomes, time.perf_counter() - started)
    return 1 if any(o.status == "failed" for o in outcomes) else 0


class ProgressBar:
    """``[#####-----] 5/10  ok 4  skipped 0  failed 1  last NAME`` on stderr (one redrawn line
    on a terminal, one line per recording otherwise)."""

    def __init__(self, total: int, enabled: bool = True, width: int = 24):
        self.total, self.enabled, self.width = total, enabled, width
        self.counts = {"ok": 0, "skipped": 0, "failed": 0}
        self.tty = sys.stderr.isatty()

    def update(self, outcome, done: int, total: int) -> None:
        self.counts[outcome.status] += 1
        if not self.enabled:
            return
        filled = round(self.width * done / max(total, 1))
        counts = "  ".join(f"{k} {v}" for k, v in self.counts.items())
        line = (f"[{'#' * filled}{'-' * (self.width - filled)}] {done}/{total}  {counts}  "
                f"{outcome.status} {outcome.job.name}")
        if self.tty:
            print(f"\r\033[K{line}", end="", file=sys.stderr, flush=True)
        else:
            print(line, file=sys.stderr, flush=True)

    def close(self) -> None:
        if self.enabled and self.tty:
            print(file=sys.stderr)


def print_summary(outcomes, seconds: float) -> None:
    """The table on stdout: recording, status, seconds, faces or the cause."""
    width = max([len(o.job.name) for o in outcomes] + [9])
    print(f"{'recording':<{width}}  {'status':<7}  {'time_s':>7}  detail")
    for o in outcomes:
        detail = o.cause if o.status != "ok" else f"{o.figures.get('faces')} faces"
        time_s = f"{o.seconds:7.1f}" if o.status != "skipped" else f"{'-':>7}"
        print(f"{o.job.name:<{width}}  {o.status:<7}  {time_s}  {detail}")
    counts = {s: sum(o.status == s for o in outcomes) for s in ("ok", "skipped", "failed")}
    print(f"{len(outcomes)} recordings in {seconds:.1f} s: " +
          ", ".join(f"{v} {k}" for k, v in counts.items()))
