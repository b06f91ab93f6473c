"""`scanstation replay RECORDING [-o DIR] [--lam F]`: re-run processing and reconstruction."""

from __future__ import annotations

import logging

log = logging.getLogger("capture.cli")


def add_parser(subparsers) -> None:
    from .scan import add_engine_options

    parser = subparsers.add_parser(
        "replay", help="rebuild a scan's mesh from its recording (same seed, same mesh)")
    parser.add_argument("recording", help="recording.mcap, or a scan folder (all its segments)")
    parser.add_argument("-o", "--output", default="out/replay", metavar="DIR",
                        help="output folder (default: out/replay)")
    add_engine_options(parser)
    parser.set_defaults(run=run)


def run(args) -> int:
    from capture.replay import replay_runner

    from .scan import cluster_executor, engine_overrides, finish, progress_printer

    executor = cluster_executor(args)
    try:
        runner = replay_runner(args.recording, args.output, workers=args.workers,
                               executor=executor, **engine_overrides(args))
        log.info("replaying %d views from %s", runner.plan.n_views, args.recording)
        runner.subscribe(progress_printer())
        return finish(runner.start())
    finally:
        if executor is not None:
            executor.shutdown(wait=False, cancel_futures=True)
