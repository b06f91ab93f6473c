"""`scanstation serve`: the headless daemon (HTTP API, live events, web page) on uvicorn."""

from __future__ import annotations

import logging
import os
from pathlib import Path

log = logging.getLogger("capture.cli")

DEFAULT_STATE_DIR = "~/.local/state/scanstation"


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "serve",
        help="run the scan station daemon: HTTP API, live events and the web page",
        description="Serve the scan station over HTTP (API docs at /docs, web page at /). On "
        "any address but loopback every API request needs the bearer token, which is made at "
        "first start, stored in STATE_DIR/token (mode 0600) and printed once.",
    )
    parser.add_argument("--host", default="127.0.0.1", help="address to bind (127.0.0.1)")
    parser.add_argument("--port", type=int, default=8765, help="TCP port (8765)")
    parser.add_argument(
        "--state-dir",
        default=os.environ.get("SCANSTATION_STATE_DIR", DEFAULT_STATE_DIR),
        help=f"job store, scans and token ($SCANSTATION_STATE_DIR or {DEFAULT_STATE_DIR})",
    )
    parser.add_argument("--max-body", type=int, default=1 << 20, metavar="BYTES",
                        help="largest request body accepted (1 MiB)")
    parser.add_argument("--access-log", action="store_true", help="log every request")
    from .scan import add_cluster_option

    add_cluster_option(parser)  # every scan the daemon runs fits on that one cluster
    parser.set_defaults(run=run)


def run(args) -> int:
    import uvicorn

    from capture.daemon.app import create_app
    from capture.daemon.auth import TOKEN_FILE, is_loopback, load_or_create_token

    if not 0 <= args.port <= 65535:
        raise ValueError(f"--port must be in [0, 65535], got {args.port}")
    if args.max_body < 0:
        raise ValueError(f"--max-body must be >= 0 bytes, got {args.max_body}")
    state_dir = Path(args.state_dir).expanduser()
    state_dir.mkdir(parents=True, exist_ok=True, mode=0o700)
    token, created = load_or_create_token(state_dir)
    required = not is_loopback(args.host)
    if created:
        print(f"API token (shown once; kept in {state_dir / TOKEN_FILE}): {token}", flush=True)
    log.info("state dir %s; %s", state_dir, "bearer token required" if required
             else "loopback only: no token needed")
    options = {}
    if args.cluster:
        import functools

        from capture.daemon.jobs import default_runner_factory
        from capture.executors import make_executor

        make_executor(args.cluster, warm_up=False).shutdown()  # unreachable: one-line error now
        options["runner_factory"] = functools.partial(default_runner_factory,
                                                      cluster=args.cluster)
        log.info("scans fit on the Dask cluster %s", args.cluster)
    app = create_app(state_dir, token=token, require_token=required,
                     max_body_bytes=args.max_body, loopback_hosts_only=not required, **options)
    level = logging.getLogger("capture").level
    logging.getLogger("uvicorn").setLevel(level)
    logging.getLogger("uvicorn.access").setLevel(level if args.access_log else logging.WARNING)
    uvicorn.run(app, host=args.host, port=args.port, log_config=None,
                timeout_graceful_shutdown=5, access_log=args.access_log)
    return 0
