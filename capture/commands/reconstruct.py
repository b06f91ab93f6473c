"""`scanstation reconstruct INPUT -o OUTPUT`: a point cloud file in, a mesh file out."""

from __future__ import annotations

import logging

log = logging.getLogger("capture.cli")


def add_reconstruction_options(parser, *, defaults=True) -> None:
    """Options shared by every command that reconstructs (reconstruct, scan, replay)."""
    from reconstruct.pipeline import DEFAULT_DEPTH, DEFAULT_LAM

    parser.add_argument("--lam", type=float, default=DEFAULT_LAM, help="spline smoothing λ")
    add_variance_option(parser)
    add_extend_option(parser)
    parser.add_argument(
        "--depth", type=int, default=DEFAULT_DEPTH, help=f"boundary path depths ({DEFAULT_DEPTH})"
    )
    parser.add_argument(
        "--embedding",
        choices=("auto", "isomap", "mlle", "landmark"),
        default="auto",
        help="3D→2D embedding (default: chosen by cloud size)",
    )
    parser.add_argument("--neighbors", type=int, default=None, help="K (default: automatic)")
    parser.add_argument("--max-layers", type=int, default=2, help="MLP hidden layers (max)")
    parser.add_argument("--max-neurons", type=int, default=20, help="neurons per layer (max)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (same seed, same mesh)")


def add_variance_option(parser, default="local") -> None:
    parser.add_argument(
        "--variance", choices=("local", "global"), default=default,
        help="variance in the spline's s = λ·m·var: 'local' (jaggedness of the boundary "
        "samples, λ≈1; default) or 'global' (spread about the centroid, the paper's literal "
        "rule, λ≈0.002)")


def add_extend_option(parser, default="auto") -> None:
    parser.add_argument(
        "--extend", type=_extend, default=default, metavar="auto|border|SPACINGS",
        help="grow the boundary outward before meshing: 'auto' (default) out to the outermost "
        "samples, 'border' to the estimated true border, or a number of point spacings")


def _number(text: str) -> float:
    """``text`` as a float; NaN when it is not a number (every bound then refuses it)."""
    try:
        return float(text)
    except ValueError:
        return float("nan")


def _extend(text: str):
    if text in ("auto", "border"):
        return text
    value = _number(text)
    if not value >= 0:  # also NaN
        import argparse

        raise argparse.ArgumentTypeError(f"expected auto, border or a number >= 0, got {text!r}")
    return value


def reconstructor_from_args(args):
    from reconstruct.pipeline import SurfaceReconstructor

    return SurfaceReconstructor(
        lam=args.lam,
        variance=args.variance,
        extend=args.extend,
        depth=args.depth,
        embedding=args.embedding,
        n_neighbors=args.neighbors,
        max_layers=args.max_layers,
        max_neurons=args.max_neurons,
        random_state=args.seed,
    )


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "reconstruct",
        help="turn a noisy point cloud (PLY, XYZ/CSV, NPY) into a mesh (PLY, OBJ, STL, GLB)",
    )
    parser.add_argument("input", help="point cloud file: .ply, .pcd (PCL's, not compressed), "
                        ".npy, or text (.xyz .txt .csv .pts: x y z first on each row, by spaces, "
                        "tabs, commas or semicolons)")
    parser.add_argument("-o", "--output", required=True, help="mesh file; format by extension")
    add_reconstruction_options(parser)
    from reconstruct.pipeline import MAX_POINTS
    from reconstruct.validation import ATLAS_POINTS

    parser.add_argument(
        "--max-points", type=points_limit, default=MAX_POINTS, metavar="N|all",
        help=f"fit one chart on a random N of a denser cloud's points (default {MAX_POINTS}; "
        "its mesh has about as many vertices), or on all")
    parser.add_argument(
        "--atlas-points", type=points_limit, default=ATLAS_POINTS, metavar="N|all",
        help=f"an atlas charts a random N of a denser cloud's points (default {ATLAS_POINTS}; "
        "at most --max-points), or all: more keep finer detail, in more time and memory, but "
        "make smooth objects noisier")
    parser.add_argument(
        "--atlas", choices=("auto", "never", "always"), default="auto",
        help="fit an atlas of charts when one chart cannot hold the cloud (auto, default), "
        "never (one chart, with a warning), or always (a closed object whose walls are "
        "thinner than the noise: one chart meshes them as one open sheet)")
    parser.add_argument(
        "--closed", choices=("auto", "yes", "no"), default="auto",
        help="join an atlas as the boundary of a volume when its charts say the cloud is "
        "closed (auto, default), always (yes), or as an open surface (no)")
    parser.add_argument(
        "--voxel", type=_voxel, default=0.5, metavar="SPACINGS",
        help="grid spacing of an atlas's join, in median point spacings (default 0.5)")
    parser.add_argument("--save", metavar="STATE", help="also save the state for `remesh`")
    parser.set_defaults(run=run)


def _voxel(text: str) -> float:
    value = _number(text)
    if not 0 < value < float("inf"):  # also NaN
        import argparse

        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}")
    return value


def points_limit(text: str):
    """A ``--max-points``-like option's value: a whole number >= 100, or None for "all"."""
    import argparse

    from reconstruct.errors import InvalidInputError
    from reconstruct.validation import MIN_MAX_POINTS, check_max_points

    if text == "all":
        return None
    try:
        value = int(text)
        check_max_points(value)
    except (ValueError, InvalidInputError):
        raise argparse.ArgumentTypeError(
            f"expected all or a whole number >= {MIN_MAX_POINTS}, got {text!r}") from None
    return value


def run(args) -> int:
    from reconstruct.io import check_mesh_path, check_output_path, read_points, write_mesh

    check_mesh_path(args.output, inputs=[args.input])  # fail before the long work, not after
    if args.save:
        check_output_path(args.save, inputs=[args.input, args.output])
    points = read_points(args.input)
    log.info("read %d points from %s", len(points), args.input)
    closed = {"auto": None, "yes": True, "no": False}[args.closed]
    model = reconstructor_from_args(args).set_params(
        max_points=args.max_points, atlas=args.atlas, closed=closed, voxel=args.voxel,
        atlas_points=args.atlas_points,
    ).fit(points)
    write_mesh(model.mesh_, args.output)
    log.info(
        "wrote %s (%d vertices, %d faces)",
        args.output,
        len(model.mesh_.vertices),
        len(model.mesh_.faces),
    )
    if args.save:
        model.save(args.save)
        log.info("saved state to %s (re-mesh with `scanstation remesh`)", args.save)
    return 0
