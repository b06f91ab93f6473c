"""`scanstation remesh STATE -o OUTPUT [--lam F] [--depth N]`: new mesh, no retraining."""

from __future__ import annotations

import logging

log = logging.getLogger("capture.cli")


def add_parser(subparsers) -> None:
    from .reconstruct import add_extend_option, add_variance_option

    parser = subparsers.add_parser(
        "remesh", help="re-mesh a saved reconstruction with a new λ / depth (no retraining)"
    )
    parser.add_argument("state", help="state file written by `reconstruct --save`")
    parser.add_argument("-o", "--output", required=True, help="mesh file; format by extension")
    parser.add_argument("--lam", type=float, default=None, help="spline smoothing λ")
    parser.add_argument("--depth", type=int, default=None, help="boundary path depths")
    parser.add_argument("--spacing", type=float, default=None, help="grid spacing (2D units)")
    add_variance_option(parser, default=None)
    add_extend_option(parser, default=None)
    parser.set_defaults(run=run)


def run(args) -> int:
    from reconstruct.io import check_mesh_path, write_mesh
    from reconstruct.pipeline import SurfaceReconstructor

    check_mesh_path(args.output)
    model = SurfaceReconstructor.load(args.state)
    mesh = model.remesh(lam=args.lam, depth=args.depth, grid_spacing=args.spacing,
                        variance=args.variance, extend=args.extend)
    write_mesh(mesh, args.output)
    log.info("wrote %s (%d vertices, %d faces)", args.output, len(mesh.vertices), len(mesh.faces))
    return 0
