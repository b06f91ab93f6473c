"""`scanstation demo`: reconstruct a built-in noisy shape, report quality against the truth."""

from __future__ import annotations

import logging
from pathlib import Path

log = logging.getLogger("capture.cli")


def add_parser(subparsers) -> None:
    from .reconstruct import add_reconstruction_options

    parser = subparsers.add_parser(
        "demo", help="reconstruct a built-in synthetic noisy shape (no hardware, no files)"
    )
    parser.add_argument("--shape", default="saddle", help="built-in shape (default: saddle)")
    parser.add_argument("--points", type=int, default=1600, help="number of points")
    parser.add_argument(
        "--noise", type=float, default=0.01, help="noise σ as a fraction of the diagonal"
    )
    parser.add_argument("-o", "--output", default="out/demo.ply", help="mesh file to write")
    add_reconstruction_options(parser)
    parser.set_defaults(run=run)


def run(args) -> int:
    from reconstruct.io import check_mesh_path, write_mesh
    from reconstruct.metrics import surface_report
    from sim.shapes import SHAPES, make_shape

    from .reconstruct import reconstructor_from_args

    if args.shape not in SHAPES:
        raise ValueError(f"unknown shape {args.shape!r} (choose from {', '.join(SHAPES)})")
    if not 0 <= args.noise < float("inf"):  # (NaN too)
        raise ValueError(f"--noise must be a finite number >= 0, got {args.noise}")
    Path(args.output).parent.mkdir(parents=True, exist_ok=True)
    check_mesh_path(args.output)  # before the fit, not after
    shape = make_shape(args.shape, args.points, noise=args.noise, random_state=args.seed)
    log.info("%s: %d points, noise σ=%.3g", shape.name, len(shape.points), shape.noise_sigma)
    model = reconstructor_from_args(args).fit(shape.points)
    write_mesh(model.mesh_, args.output)
    report = surface_report(model.mesh_, shape.points, shape.truth)
    print(
        f"wrote {args.output}: {len(model.mesh_.vertices)} vertices, {len(model.mesh_.faces)} faces"
    )
    for key, value in report.items():
        print(f"  {key:<16} {value:.4g}")
    return 0
