"""Station calibration: where the turntable axis is in the camera frame, as a value.

`Calibration` holds the intrinsics and the camera → table transform, and reads and writes them
as JSON. Estimating it from views of a target is `capture.axis_calibration`'s.

Frames: camera frame as OpenCV (x right, y down, z forward), mm. Table frame: z up along the axis,
origin where the axis meets the plate, y along the camera's viewing direction projected on the
plate (away from the camera), x = y × z.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

FORMAT = "scanstation-calibration/1"


class CalibrationError(ValueError):
    """A calibration that cannot be estimated, loaded or used (message names the cause)."""


def _rigid_inverse(m: np.ndarray) -> np.ndarray:
    inv = np.eye(4)
    inv[:3, :3] = m[:3, :3].T
    inv[:3, 3] = -m[:3, :3].T @ m[:3, 3]
    return inv


def _rotation_z(degrees: float) -> np.ndarray:
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    m = np.eye(4)
    m[:2, :2] = [[c, -s], [s, c]]
    return m


@dataclasses.dataclass(frozen=True, eq=False)
class Calibration:
    """Intrinsics and the camera → table rigid transform of one station.

    intrinsics : (3, 3) pinhole matrix, pixels.  camera_to_table : (4, 4) rigid transform, mm.
    rotation_sign : +1 when a positive table angle turns the plate counter-clockwise seen from
        above (right-handed about the table's z), else -1.
    residual_mm : RMS residual of the axis circle fit (0 for a known truth).
    """

    intrinsics: np.ndarray
    camera_to_table: np.ndarray
    rotation_sign: int = 1
    residual_mm: float = 0.0

    def __post_init__(self):
        k = np.array(self.intrinsics, dtype=np.float64)
        m = np.array(self.camera_to_table, dtype=np.float64)
        if (
            k.shape != (3, 3)
            or not (k[0, 0] > 0 and k[1, 1] > 0)
            or not np.allclose(k[2], [0, 0, 1])
        ):
            raise CalibrationError(f"intrinsics must be a (3, 3) pinhole matrix, got {k.tolist()}")
        if m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise CalibrationError(f"camera_to_table must be a finite (4, 4) matrix, got {m.shape}")
        r = m[:3, :3]
        rigid = np.allclose(r @ r.T, np.eye(3), atol=1e-6) and np.linalg.det(r) > 0
        if not rigid or not np.allclose(m[3], [0, 0, 0, 1]):
            raise CalibrationError("camera_to_table is not a rigid transform (rotation + shift)")
        if self.rotation_sign not in (1, -1):
            raise CalibrationError(f"rotation_sign must be +1 or -1, got {self.rotation_sign}")
        for name, value in (("intrinsics", k), ("camera_to_table", m)):
            value.flags.writeable = False
            object.__setattr__(self, name, value)
        object.__setattr__(self, "rotation_sign", int(self.rotation_sign))
        object.__setattr__(self, "residual_mm", float(self.residual_mm))

    @property
    def table_to_camera(self) -> np.ndarray:
        """(4, 4) inverse of ``camera_to_table``."""
        return _rigid_inverse(self.camera_to_table)

    @property
    def axis_origin(self) -> np.ndarray:
        """(3,) where the axis meets the plate, camera frame, mm."""
        return self.table_to_camera[:3, 3]

    @property
    def axis_direction(self) -> np.ndarray:
        """(3,) unit vector up the axis, camera frame."""
        return self.table_to_camera[:3, 2]

    def table_transform(self, angle_deg: float) -> np.ndarray:
        """(4, 4) camera frame at table angle ``angle_deg`` → object frame (the table at 0°)."""
        return _rotation_z(-self.rotation_sign * angle_deg) @ self.camera_to_table

    @classmethod
    def from_axis(cls, intrinsics, axis_origin, axis_direction, rotation_sign=1, residual_mm=0.0):
        """Build from the axis in camera coordinates (origin on the plate, direction up)."""
        z = np.asarray(axis_direction, dtype=np.float64)
        z = z / np.linalg.norm(z)
        forward = np.array([0.0, 0.0, 1.0]) - z[2] * z
        if np.linalg.norm(forward) < 1e-6:  # looking straight along the axis
            forward = np.array([0.0, 1.0, 0.0]) - z[1] * z
        y = forward / np.linalg.norm(forward)
        x = np.cross(y, z)
        table_to_camera = np.eye(4)
        table_to_camera[:3, :3] = np.column_stack([x, y, z])
        table_to_camera[:3, 3] = axis_origin
        return cls(intrinsics, _rigid_inverse(table_to_camera), rotation_sign, residual_mm)

    @classmethod
    def from_sim(cls, camera) -> Calibration:
        """The true calibration of a simulated camera (from its ground-truth pose).

        Reads ``camera.camera_to_table`` (4, 4) (or ``camera.true_pose``, taken as camera →
        table) and ``camera.rotation_sign`` (default +1).
        """
        pose = getattr(camera, "camera_to_table", None)
        if pose is None:
            pose = getattr(camera, "true_pose", None)
        if pose is None:
            raise CalibrationError(f"{type(camera).__name__} exposes no true pose")
        return cls(camera.intrinsics, np.asarray(pose), getattr(camera, "rotation_sign", 1))

    def to_json(self) -> str:
        return json.dumps(
            {
                "format": FORMAT,
                "intrinsics": self.intrinsics.tolist(),
                "camera_to_table": self.camera_to_table.tolist(),
                "rotation_sign": self.rotation_sign,
                "residual_mm": self.residual_mm,
            },
            indent=1,
        )

    @classmethod
    def from_json(cls, text: str) -> Calibration:
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise CalibrationError(f"calibration is not valid JSON: {exc}") from exc
        if not isinstance(data, dict) or data.get("format") != FORMAT:
            raise CalibrationError(f"not a calibration file (expected format {FORMAT!r})")
        missing = [k for k in ("intrinsics", "camera_to_table") if k not in data]
        if missing:
            raise CalibrationError(f"calibration lacks {', '.join(missing)}")
        try:
            k = np.array(data["intrinsics"], dtype=np.float64)
            m = np.array(data["camera_to_table"], dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise CalibrationError(f"calibration matrices are not numeric: {exc}") from exc
        return cls(k, m, data.get("rotation_sign", 1), data.get("residual_mm", 0.0))

    def save(self, path) -> None:
        Path(path).write_text(self.to_json())

    @classmethod
    def load(cls, path) -> Calibration:
        try:
            text = Path(path).read_text()
        except OSError as exc:
            raise CalibrationError(f"cannot read calibration {path}: {exc.strerror}") from exc
        return cls.from_json(text)
