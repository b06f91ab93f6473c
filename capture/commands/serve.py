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
    parser.add_argument(
        "--allow-device", action="append", metavar="URL",
        default=os.environ.get("SCANSTATION_ALLOW_DEVICES", "").split(),
        help="a device that scans may use beyond serial ports and loopback addresses, e.g. "
        "socket://10.0.0.5:23 (a ser2net turntable; no port: any port) or oak://192.168.1.44; "
        "repeat for more ($SCANSTATION_ALLOW_DEVICES, space-separated)")
    parser.add_argument(
        "--object-dir", metavar="DIR", default=os.environ.get("SCANSTATION_OBJECT_DIR"),
        help="folder of mesh files that scans may name as the simulated camera's object "
        "(default: built-in objects only; $SCANSTATION_OBJECT_DIR)")
    parser.add_argument("--max-object-mib", type=float, default=256, metavar="MIB",
                        help="largest object file accepted (256 MiB)")
    parser.add_argument("--object-memory-mib", type=float, default=2048, metavar="MIB",
                        help="memory a scan process may take to load its object (2048 MiB)")
    parser.add_argument("--max-scans", type=int, default=2, metavar="N",
                        help="scans without a real device (simulated, re-processing) at once; "
                        "a real device runs one scan at a time (2)")
    parser.add_argument("--max-queued", type=int, default=8, metavar="N",
                        help="scans waiting for a slot before new ones get 429 (8)")
    parser.add_argument("--access-log", action="store_true", help="log every request")
    from .scan import add_cluster_option

    add_cluster_option(parser)  # every scan the daemon runs fits on that one cluster
    parser.set_defaults(run=run)


def run(args) -> int:
    import uvicorn

    from capture.daemon.app import create_app, prepare_state_dir
    from capture.daemon.auth import TOKEN_FILE, is_loopback, load_or_create_token
    from capture.daemon.store import StoreError

    if not 0 <= args.port <= 65535:
        raise ValueError(f"--port must be in [0, 65535], got {args.port}")
    if args.max_body < 0:
        raise ValueError(f"--max-body must be >= 0 bytes, got {args.max_body}")
    if args.max_scans < 1 or args.max_queued < 0:
        raise ValueError("--max-scans must be >= 1 and --max-queued >= 0")
    if not (args.max_object_mib > 0 and args.object_memory_mib > 0):
        raise ValueError("--max-object-mib and --object-memory-mib must be > 0")
    object_dir = None
    if args.object_dir:
        object_dir = Path(args.object_dir).expanduser()
        if not object_dir.is_dir():
            raise ValueError(f"--object-dir {object_dir} is not a folder")
    os.umask(0o077)  # the job store, recordings, meshes: the daemon's user's only
    state_dir = Path(args.state_dir).expanduser()
    try:  # checked (repaired) before serving: a damaged store is one line, not a traceback
        prepare_state_dir(state_dir).close()
    except StoreError as exc:
        raise SystemExit(f"scanstation: error: {exc}") from None
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
                     max_body_bytes=args.max_body, loopback_hosts_only=not required,
                     allow_devices=args.allow_device, object_dir=object_dir,
                     max_object_bytes=int(args.max_object_mib * 2**20),
                     object_memory_bytes=int(args.object_memory_mib * 2**20),
                     max_running=args.max_scans, max_queued=args.max_queued, **options)
    level = logging.getLogger("capture").level
    logging.getLogger("uvicorn").setLevel(level)
    logging.getLogger("uvicorn.access").setLevel(level if args.access_log else logging.WARNING)
    uvicorn.run(app, host=args.host, port=args.port, log_config=None,
                timeout_graceful_shutdown=5, access_log=args.access_log)
    return 0
