"""`scanstation calibrate [--camera URL] [--turntable URL] -o calibration.json`."""

from __future__ import annotations

import logging

log = logging.getLogger("capture.cli")


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "calibrate", help="find the turntable axis from the dumbbell target (simulated without "
        "URLs)")
    parser.add_argument("--camera", metavar="URL", help="depth camera (default: simulated, "
                        "showing the target)")
    parser.add_argument("--turntable", metavar="URL", help="turntable (default: simulated)")
    parser.add_argument("--views", type=int, default=12, help="target views over one turn (12)")
    parser.add_argument("-o", "--output", default="calibration.json", metavar="FILE",
                        help="calibration JSON to write (default: calibration.json)")
    parser.set_defaults(run=run)


def run(args) -> int:
    import tempfile
    from pathlib import Path

    import numpy as np

    from capture.axis_calibration import DumbbellTarget, calibrate
    from capture.calibration import Calibration
    from capture.station import follow_turntable, is_simulated, station_urls
    from drivers.registry import open_camera, open_turntable

    if args.views < 4:
        raise ValueError(f"--views must be >= 4 to fit the axis, got {args.views}")
    Path(args.output).parent.mkdir(parents=True, exist_ok=True)
    target = DumbbellTarget()
    with tempfile.TemporaryDirectory(prefix="scanstation-target-") as tmp:
        target_file = None
        if args.camera is None or is_simulated(args.camera):
            target_file = Path(tmp) / "dumbbell.stl"
            target.mesh().export(target_file)
        camera_url, turntable_url = station_urls(args.camera, args.turntable,
                                                 object=target_file and str(target_file))
        angles = tuple(float(a) for a in np.arange(args.views) * 360.0 / args.views)
        with open_camera(camera_url) as camera, open_turntable(turntable_url) as table:
            follow_turntable(camera, table)
            log.info("capturing the target at %d angles", len(angles))
            calibration = calibrate(camera, table, angles=angles, target=target)
            truth = Calibration.from_sim(camera) if is_simulated(camera_url) else None
    calibration.save(args.output)
    print(f"wrote {args.output}: axis fit rms {calibration.residual_mm:.3f} mm, rotation sign "
          f"{calibration.rotation_sign:+d}")
    if truth is not None:
        distance, angle = axis_errors(calibration, truth)
        print(f"  against the simulator's true axis: {distance:.3f} mm, {angle:.3f}°")
    return 0


def axis_errors(estimated, truth) -> tuple[float, float]:
    """(distance mm between the estimated and true axis origins on the plate, angle ° between
    the axes)."""
    import numpy as np

    cosine = np.clip(estimated.axis_direction @ truth.axis_direction, -1, 1)
    distance = np.linalg.norm(estimated.axis_origin - truth.axis_origin)
    return float(distance), float(np.degrees(np.arccos(cosine)))
