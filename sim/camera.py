"""``sim://camera``: an OAK-D-like depth camera that renders the simulated station.

    sim://camera?object=vase&seed=0&station=default
    sim://camera?object=/path/to/mesh.stl&noise=0&width=320&height=200&disconnect_after=5

The object stands on the turntable plate (a disc, top at z = 0) in front of a wall and turns with
the station's simulated turntable: each ``grab`` renders the table's true angle at that moment.
`SimCamera.follow` makes it render at the angle any other `Turntable` reports instead (a GRBL
board on a real port: hardware in the loop for `scanstation scan` and `calibrate`).
Optics: 640×400, 72° horizontal field of view, 75 mm stereo baseline, looking at the axis from
``distance`` mm, ``elevation`` degrees above the plate. Options (URL query or keywords):
``noise`` (scale of the disparity error; 0 = ideal depth), ``seed``, ``engine`` (numpy | embree),
``realtime=1`` (pace grabs at ``fps``), ``rotation_sign`` (+1: a positive table angle turns the
object counter-clockwise seen from above), ``disconnect_after=N`` (the N+1-th grab finds the
camera unplugged, once; reopening reconnects it).
"""

from __future__ import annotations

import threading
import time
import urllib.parse

import numpy as np
import trimesh

from drivers.base import DepthCamera, Frame
from drivers.errors import DeviceDisconnected, DeviceError, InvalidDeviceURL
from sim.objects import load_object
from sim.render import ENGINES, intrinsics_for, look_at, make_renderer
from sim.station import get_station
from sim.stereo_noise import StereoNoise

#: option -> (type, default)
OPTIONS: dict[str, tuple[type, object]] = {
    "object": (str, "vase"), "station": (str, "default"), "engine": (str, "numpy"),
    "noise": (float, 1.0), "seed": (int, 0), "width": (int, 640), "height": (int, 400),
    "fps": (float, 30.0), "realtime": (int, 0), "hfov": (float, 72.0),
    "distance": (float, 420.0), "elevation": (float, 25.0), "target_height": (float, 60.0),
    "plate_radius": (float, 100.0), "rotation_sign": (int, 1), "disconnect_after": (int, -1),
}
PLATE_THICKNESS_MM = 5.0


def parse_options(url: str, **overrides) -> dict:
    """The camera options of a ``sim://camera?...`` URL merged with keyword ``overrides``."""
    parts = urllib.parse.urlsplit(url)
    if parts.scheme != "sim" or parts.netloc not in ("camera", ""):
        raise InvalidDeviceURL(f"not a simulated camera URL: {url!r}")
    # blank values kept: an empty ``object=`` is an error, not the default object
    given = {k: v[-1] for k, v in urllib.parse.parse_qs(parts.query,
                                                         keep_blank_values=True).items()}
    given.update({k: v for k, v in overrides.items() if v is not None})  # None: default
    unknown = sorted(set(given) - set(OPTIONS))
    if unknown:
        raise InvalidDeviceURL(f"unknown parameter(s) {', '.join(unknown)} in {url!r}")
    options = {}
    for key, (kind, default) in OPTIONS.items():
        value = given.get(key, default)
        try:
            options[key] = kind(value)
        except (TypeError, ValueError) as exc:
            raise InvalidDeviceURL(f"parameter {key}={value!r} is not a {kind.__name__} in "
                                   f"{url!r}") from exc
    checks = [
        (options["width"] >= 8 and options["height"] >= 8, "width and height must be >= 8"),
        (0 < options["hfov"] < 170, "hfov must be between 0 and 170 degrees"),
        (options["noise"] >= 0, "noise must be >= 0"),
        (options["fps"] > 0, "fps must be > 0"),
        (options["distance"] > 0, "distance must be > 0"),
        (options["rotation_sign"] in (1, -1), "rotation_sign must be 1 or -1"),
        (options["engine"] in ENGINES, f"engine must be one of {', '.join(ENGINES)}"),
    ]
    for ok, message in checks:
        if not ok:
            raise InvalidDeviceURL(f"{message} in {url!r}")
    return options


def station_background(plate_radius: float, wall_distance: float) -> trimesh.Trimesh:
    """The static scene, table frame, mm: the plate (top at z = 0, symmetric about the axis, so
    it looks the same at every angle) and a wall ``wall_distance`` behind the axis."""
    plate = trimesh.creation.cylinder(plate_radius, PLATE_THICKNESS_MM, sections=128)
    plate.apply_translation([0, 0, -PLATE_THICKNESS_MM / 2])
    wall = trimesh.creation.box((1600.0, 10.0, 1400.0))
    wall.apply_translation([0, wall_distance + 5.0, 300.0])
    return trimesh.util.concatenate([plate, wall])


class SimCamera(DepthCamera):
    """Renders the station's object at the simulated turntable's current angle."""

    schemes = ("sim",)

    def __init__(self, url: str = "sim://camera", **options):
        super().__init__(url)
        self.options = parse_options(url, **options)
        o = self.options
        self.station = o["station"]
        self.shape = (o["height"], o["width"])
        self.rotation_sign = o["rotation_sign"]
        self._intrinsics = intrinsics_for(o["width"], o["height"], o["hfov"])
        elevation = np.radians(o["elevation"])
        eye = [0.0, -o["distance"] * np.cos(elevation),
               o["target_height"] + o["distance"] * np.sin(elevation)]
        #: (4, 4) camera frame → table frame (z up the axis, origin on the plate, y away from the
        #: camera), the ground truth that `Calibration.from_sim` reads.
        self.camera_to_table = look_at(eye, [0.0, 0.0, o["target_height"]])
        self.noise_model = StereoNoise(sigma_px=StereoNoise.sigma_px * o["noise"])
        self._rng = np.random.default_rng(o["seed"])  # one noise stream, across reconnects
        self._lock = threading.Lock()
        self._object = None
        self._renderer = None
        self._background = None
        self._frames = 0
        self._unplugged = False
        self._disconnected_once = False
        self._last_grab = None
        self._followed = None  # a Turntable whose reported angle is rendered, or None

    @classmethod
    def from_url(cls, url: str, **options) -> SimCamera:
        return cls(url, **options)

    @classmethod
    def discover(cls) -> list[str]:
        return ["sim://camera"]

    @property
    def intrinsics(self) -> np.ndarray:
        return self._intrinsics.copy()

    @property
    def table_to_camera(self) -> np.ndarray:
        """(4, 4) inverse of ``camera_to_table``."""
        r, t = self.camera_to_table[:3, :3], self.camera_to_table[:3, 3]
        out = np.eye(4)
        out[:3, :3], out[:3, 3] = r.T, -r.T @ t
        return out

    @property
    def renderer(self):
        """The object's renderer (`sim.render.MeshRenderer` of the chosen engine)."""
        self._load_object()
        return self._renderer

    def follow(self, turntable) -> None:
        """Render at the angle ``turntable`` reports, whatever its backend. A simulated
        turntable of this camera's station is followed already (its firmware's true angle), so
        it is left to the station; None goes back to the station."""
        same_station = getattr(turntable, "station", None) == self.station
        self._followed = None if turntable is None or same_station else turntable

    def table_angle(self) -> float:
        """Degrees: the followed turntable's reported angle, else the station's true angle."""
        if self._followed is not None:
            return float(self._followed.angle)
        return get_station(self.station).angle_degrees()

    def true_object_mesh(self) -> trimesh.Trimesh:
        """The object in the table frame at table angle 0 (ground truth), mm."""
        return self._load_object().copy()

    # -- life cycle ------------------------------------------------------------------------------
    def _open(self) -> None:
        self._load_object()
        if self._background is None:
            scene = station_background(self.options["plate_radius"], self.options["distance"])
            renderer = make_renderer(scene.vertices, scene.faces, cull=True)
            self._background = renderer.render(self.table_to_camera, self._intrinsics, self.shape)
        self._unplugged = False
        self._last_grab = None

    def _close(self) -> None:
        """Nothing to release: the simulated camera holds no threads or handles."""

    def reconnect(self) -> None:
        """Plug the camera back in and reopen it (what a driver does after a USB reset)."""
        self.close()
        self.open()

    def _load_object(self) -> trimesh.Trimesh:
        if self._object is None:
            mesh = load_object(self.options["object"])
            closed = bool(mesh.is_watertight and mesh.is_winding_consistent)
            engine = self.options["engine"]
            self._renderer = make_renderer(mesh.vertices, mesh.faces, closed, engine)
            self._object = mesh
        return self._object

    # -- frames ----------------------------------------------------------------------------------
    def render(self, angle_deg: float) -> tuple[np.ndarray, np.ndarray]:
        """Ideal depth (H, W) float32 mm and |incidence cosine| (H, W) of the scene with the
        table at ``angle_deg``."""
        self._load_object()
        a = np.radians(self.rotation_sign * angle_deg)
        turn = np.eye(4)
        turn[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
        depth, cosine = self._renderer.render(self.table_to_camera @ turn, self._intrinsics,
                                              self.shape)
        if self._background is None:
            return depth, cosine
        bg_depth, bg_cosine = self._background
        nearer = (depth > 0) & ((bg_depth == 0) | (depth < bg_depth))
        return np.where(nearer, depth, bg_depth), np.where(nearer, cosine, bg_cosine)

    def grab(self, timeout: float | None = None) -> Frame:
        """The next frame: the station rendered at the turntable's angle now, with noise."""
        with self._lock:
            self._check_connected()
            if self.options["realtime"] and self._last_grab is not None:
                wait = self._last_grab + 1.0 / self.options["fps"] - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
            depth, cosine = self.render(self.table_angle())
            if self.options["noise"] > 0:
                depth_mm = self.noise_model.apply(depth, cosine, self._intrinsics[0, 0], self._rng)
            else:
                depth_mm = np.round(depth).astype(np.uint16)
            self._frames += 1
            self._last_grab = time.monotonic()
            return Frame(depth=depth_mm, timestamp=self._last_grab, sequence=self._frames)

    def _check_connected(self) -> None:
        if not self.is_open:
            raise DeviceError(f"{self.url}: camera is not open")
        if self._unplugged:
            raise DeviceDisconnected(f"{self.url}: camera disconnected (reopen to reconnect)")
        limit = self.options["disconnect_after"]
        if 0 <= limit <= self._frames and not self._disconnected_once:
            self._unplugged = self._disconnected_once = True
            raise DeviceDisconnected(f"{self.url}: camera disconnected after {limit} frames "
                                     "(simulated unplug)")
