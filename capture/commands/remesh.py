"""`scanstation remesh STATE|SCAN -o OUTPUT [--lam F] [--depth N]`: new mesh, no retraining."""

from __future__ import annotations

import logging
from pathlib import Path

log = logging.getLogger("capture.cli")

#: Options only a `reconstruct --save` state takes (a scan's engine re-meshes with λ and depth).
STATE_ONLY = ("spacing", "variance", "extend")


def add_parser(subparsers) -> None:
    from .reconstruct import add_extend_option, add_variance_option

    parser = subparsers.add_parser(
        "remesh", help="re-mesh a saved reconstruction or a scan with a new λ / depth (no "
                       "retraining)"
    )
    parser.add_argument("state", help="state file written by `reconstruct --save`, or a scan's "
                                      "folder")
    parser.add_argument("-o", "--output", required=True, help="mesh file; format by extension")
    parser.add_argument("--lam", type=float, default=None, help="spline smoothing λ")
    parser.add_argument("--depth", type=int, default=None, help="boundary path depths")
    parser.add_argument("--spacing", type=float, default=None, help="grid spacing (2D units)")
    add_variance_option(parser, default=None)
    add_extend_option(parser, default=None)
    parser.set_defaults(run=run)


def run(args) -> int:
    from reconstruct.io import check_mesh_path, write_mesh

    check_mesh_path(args.output, inputs=[args.state])
    scan = scan_folder(Path(args.state))
    mesh = _remesh_scan(scan, args) if scan is not None else _remesh_state(args)
    write_mesh(mesh, args.output)
    log.info("wrote %s (%d vertices, %d faces)", args.output, len(mesh.vertices), len(mesh.faces))
    return 0


def scan_folder(path: Path) -> Path | None:
    """The scan folder ``path`` names (itself, or the parent of its ``engine`` folder), None
    for a file; a folder holding no re-meshable scan is a `CaptureError`."""
    from capture.live.engine import STATE_DIR
    from capture.runner import CaptureError

    if not path.is_dir():
        return None
    for folder in (path, path.parent):
        if (folder / STATE_DIR / "engine.json").is_file():
            return folder
    raise CaptureError(f"{path}: a folder without a scan's reconstruction ({STATE_DIR}/"
                       f"engine.json: scanned with --no-reconstruction, or not a scan folder)")


def _remesh_scan(folder: Path, args):
    """The mesh of the scan in ``folder`` re-meshed with ``args.lam`` and ``args.depth``."""
    from capture.live.engine import EngineError, IncrementalEngine
    from capture.runner import CaptureError

    given = [f"--{name}" for name in STATE_ONLY if getattr(args, name) is not None]
    if given:
        raise CaptureError(f"{' and '.join(given)}: a scan re-meshes with --lam and --depth "
                           f"only")
    try:
        engine = IncrementalEngine.load(folder)
        engine.remesh(args.lam, args.depth)
    except EngineError as exc:
        raise CaptureError(str(exc)) from exc
    return engine.mesh


def _remesh_state(args):
    """The mesh of the `reconstruct --save` state ``args.state`` re-meshed with ``args``."""
    from reconstruct.pipeline import SurfaceReconstructor

    model = SurfaceReconstructor.load(args.state)
    return model.remesh(lam=args.lam, depth=args.depth, grid_spacing=args.spacing,
                        variance=args.variance, extend=args.extend)
