"""`scanstation scan`: capture a turntable scan, record it, reconstruct it while it turns.

With no device URLs the station is simulated. DIR receives recording.mcap, mesh.ply and
scan.json; progress goes to stderr, the summary to stdout.
"""

from __future__ import annotations

import logging

log = logging.getLogger("capture.cli")
#: `sim.objects.BUILT_IN`'s names (the CLI does not import the simulator to list them).
BUILT_IN_OBJECTS = ("vase", "bust", "box", "mug", "torus", "figurine", "hook", "sheets", "chair",
                    "knot", "tray")


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "scan", help="scan an object on the turntable (simulated station without URLs)")
    parser.add_argument("--camera", metavar="URL", help="depth camera, e.g. oak:// (default: "
                        "simulated)")
    parser.add_argument("--turntable", metavar="URL", help="turntable, e.g. grbl:///dev/ttyUSB0 "
                        "(default: simulated)")
    parser.add_argument("--views", type=int, default=36, help="views over one turn (36)")
    parser.add_argument("--object", metavar="PATH", help="mesh the simulated camera sees "
                        f"(file or built-in name: {', '.join(BUILT_IN_OBJECTS)})")
    parser.add_argument("-o", "--output", default=None, metavar="DIR",
                        help="output folder, new or empty (default: scans/scan-DATE-TIME)")
    parser.add_argument("--frames", type=int, default=3, help="frames per view, median-combined")
    parser.add_argument("--settle", type=float, default=0.1, help="seconds after each move")
    parser.add_argument("--calibration", metavar="FILE", help="station calibration JSON "
                        "(`scanstation calibrate`; required for real cameras)")
    parser.add_argument("--plan", metavar="FILE", help="a scan plan JSON (overrides the "
                        "options above)")
    parser.add_argument("--resume", metavar="DIR", help="continue an interrupted scan in DIR")
    parser.add_argument("--reconnect-timeout", type=float, default=86400.0, metavar="S",
                        help="seconds a lost device is retried while the scan is paused before "
                        "it fails (default: a day; Ctrl-C stops, recorded views are kept)")
    parser.add_argument("--no-reconstruction", action="store_true", help="capture and record "
                        "only")
    add_engine_options(parser)
    parser.set_defaults(run=run)


def add_engine_options(parser) -> None:
    """Options of the incremental engine shared by scan and replay."""
    parser.add_argument("--lam", type=float, default=None, help="spline smoothing λ")
    parser.add_argument("--depth", type=int, default=None, help="boundary path depths")
    parser.add_argument("--seed", type=int, default=None, help="random seed (same seed, same "
                        "mesh)")
    parser.add_argument("--workers", type=workers_count, default=2,
                        help="processes fitting patches (2; 1: in the scan's own)")
    add_cluster_option(parser)


def workers_count(text: str) -> int:
    """A ``--workers`` value: a whole number >= 1 (0 and -1 were taken as 1 without a word)."""
    import argparse

    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, got {text!r}")
    return value


def add_cluster_option(parser) -> None:
    """``--cluster ADDRESS``: the fits on a Dask cluster (scan, replay, reprocess, serve)."""
    parser.add_argument("--cluster", metavar="ADDRESS", default=None,
                        help="run the fits on a Dask cluster, e.g. tcp://server:8786 (needs the "
                        "'cluster' extra; default: local processes)")


def cluster_executor(args):
    """The Dask executor for ``--cluster`` (None without it: the engine's own processes)."""
    if not getattr(args, "cluster", None):
        return None
    from capture.executors import make_executor

    return make_executor(args.cluster)


def engine_overrides(args) -> dict:
    return {k: getattr(args, k) for k in ("lam", "depth", "seed") if getattr(args, k) is not None}


def progress_printer(n_total_hint: int | None = None):
    """A document subscriber logging one line per view, mesh, pause and stop (stderr)."""

    def show(document) -> None:
        kind = document.kind
        if kind == "start" and document.resumed_views:
            log.info("resuming: %d views already recorded", document.resumed_views)
        elif kind == "progress":
            log.info("view %d/%d: %d points (cloud %d)", document.views_done,
                     document.views_total, document.view_points, document.cloud_points)
        elif kind == "mesh":
            f = document.figures
            log.info("mesh v%d after %d views: %d faces (%.1f s)%s", document.version,
                     document.views, f.get("faces", 0), f.get("seconds", 0.0),
                     " — final" if document.final else "")
        elif kind == "paused":
            log.warning("paused: %s", document.message)
        elif kind == "resumed":
            log.warning("resumed: %s", document.message)

    return show


def run(args) -> int:
    import dataclasses

    from capture.plan import ScanPlan
    from capture.runner import ScanRunner

    if args.plan:
        from pathlib import Path

        plan = ScanPlan.from_json(Path(args.plan).read_text())
    elif args.resume:
        plan = None  # the recording's own
    else:
        plan = ScanPlan.turn(args.views, frames_per_view=args.frames, settle_s=args.settle,
                             reconnect_timeout_s=args.reconnect_timeout, on_device_lost="fail")
        if args.no_reconstruction:
            plan = dataclasses.replace(plan, reconstruction=None)
    if plan is not None and plan.reconstruction is not None and engine_overrides(args):
        plan = dataclasses.replace(plan, reconstruction=dataclasses.replace(
            plan.reconstruction, **engine_overrides(args)))
    out_dir = args.resume or args.output or default_output()
    executor = cluster_executor(args)
    try:
        runner = ScanRunner(plan, camera_url=args.camera, turntable_url=args.turntable,
                            object=args.object, out_dir=out_dir,
                            resume_from=args.resume, calibration=args.calibration,
                            workers=args.workers, executor=executor)
        runner.subscribe(progress_printer())
        return finish(runner.start())
    finally:
        if executor is not None:
            executor.shutdown(wait=False, cancel_futures=True)


def default_output() -> str:
    """A new folder per scan, so that a second scan never lands in the first one's folder."""
    import time

    return time.strftime("scans/scan-%Y%m%d-%H%M%S")


def finish(runner) -> int:
    """Wait for a started runner (Ctrl-C cancels it) and print the outcome; the exit code."""
    try:
        state = runner.wait()
    except KeyboardInterrupt:
        runner.cancel()
        runner.wait()
        raise
    if state != "done":
        raise_for(runner)
    stop = runner.documents[-1].to_dict()
    print(f"{state}: {runner.reason}")
    for name, path in stop.get("files", {}).items():
        print(f"  {name:<10} {path}")
    report = runner.outputs.directory / "scan.json"
    if report.is_file():
        import json

        data = json.loads(report.read_text())
        for key, value in (data.get("quality") or {}).items():
            print(f"  {key:<22} {value:.4g}")
    return 0


def raise_for(runner) -> None:
    from capture.runner import CaptureError

    if runner.state == "interrupted":
        raise KeyboardInterrupt
    raise CaptureError(f"scan {runner.state}: {runner.reason} (recorded views are kept in "
                       f"{runner.out_dir}; `scanstation scan --resume {runner.out_dir}` "
                       "continues)")
