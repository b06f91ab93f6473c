"""A station: one depth camera, one turntable and the calibration between them.

With no device URLs the station is simulated (``sim://`` devices, reached through the URL
registry like any hardware): a camera and a turntable sharing one simulated station name, so the
camera renders what the table's angle shows, and the calibration is the simulator's true pose.
Real devices need a calibration file (`scanstation calibrate`).
"""

from __future__ import annotations

import dataclasses
import logging
import urllib.parse
import uuid

from drivers.base import DepthCamera, Turntable
from drivers.errors import InvalidDeviceURL
from drivers.registry import backend_class, open_camera, open_turntable

from .calibration import Calibration, CalibrationError

log = logging.getLogger(__name__)

DEFAULT_SIM_TURNTABLE = "sim://turntable?instant=0"


def _query(url: str) -> dict[str, str]:
    return {k: v[-1] for k, v in urllib.parse.parse_qs(urllib.parse.urlsplit(url).query).items()}


def _with_params(url: str, **params) -> str:
    """``url`` with query parameters added (existing ones win)."""
    parts = urllib.parse.urlsplit(url)
    query = urllib.parse.parse_qs(parts.query, keep_blank_values=True)
    for key, value in params.items():
        if value is not None and key not in query:
            query[key] = [str(value)]
    return urllib.parse.urlunsplit(parts._replace(query=urllib.parse.urlencode(query, doseq=True)))


def is_simulated(url: str | None) -> bool:
    return url is not None and urllib.parse.urlsplit(url).scheme == "sim"


def station_urls(camera_url=None, turntable_url=None, object=None, seed: int = 0):
    """(camera URL, turntable URL) with the simulated defaults filled in.

    A missing URL becomes a simulated device; simulated devices share one station name (taken
    from whichever URL names one, else a fresh ``scan-…`` name). ``object`` picks the simulated
    camera's mesh (a built-in name or a file) and is an error with a real camera.
    """
    if object is not None and camera_url is not None and not is_simulated(camera_url):
        raise InvalidDeviceURL(f"--object needs the simulated camera, not {camera_url!r}")
    names = [_query(u).get("station") for u in (camera_url, turntable_url) if is_simulated(u)]
    station = next((n for n in names if n), None) or f"scan-{uuid.uuid4().hex[:8]}"
    if camera_url is None:
        camera_url = "sim://camera"
    if turntable_url is None:
        turntable_url = DEFAULT_SIM_TURNTABLE
    if is_simulated(camera_url):
        camera_url = _with_params(camera_url, station=station, object=object, seed=seed)
    if is_simulated(turntable_url):
        turntable_url = _with_params(turntable_url, station=station)
    return camera_url, turntable_url


@dataclasses.dataclass
class Station:
    """Open devices and their calibration. ``close()`` is safe to repeat. A recorded station
    (`recorded_station`) has no devices: its views come from a recording."""

    camera: DepthCamera | None
    turntable: Turntable | None
    calibration: Calibration
    camera_url: str
    turntable_url: str

    @property
    def intrinsics(self):
        """(3, 3) the camera's pinhole matrix (the calibration's without a camera)."""
        return self.calibration.intrinsics if self.camera is None else self.camera.intrinsics

    def describe(self) -> dict:
        return {"camera": self.camera_url, "turntable": self.turntable_url,
                "simulated": is_simulated(self.camera_url)}

    def reconnect(self, device: str) -> None:
        """Reconnect ``device`` ("camera" or "turntable"); raises while it is still gone."""
        if device == "turntable" and hasattr(self.turntable, "reconnect"):
            if not self.turntable.is_open:
                self.turntable.open()
            self.turntable.reconnect()
            return
        target = self.camera if device == "camera" else self.turntable
        target.close()
        target.open()

    def close(self) -> None:
        for device in (self.camera, self.turntable):
            if device is None:
                continue
            try:
                device.close()
            except Exception as exc:  # closing must not hide the scan's own outcome
                log.warning("closing %s failed: %s", device, exc)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def follow_turntable(camera: DepthCamera, turntable: Turntable) -> None:
    """A simulated camera renders at the angle ``turntable`` reports, whatever its backend (a
    GRBL board: hardware in the loop); other cameras see the real table anyway."""
    if hasattr(camera, "follow"):
        camera.follow(turntable)


def recorded_station(recording) -> Station:
    """The station a `capture.recording.Recording` was made on, without devices: its recorded
    calibration, and its camera URL (so that a simulated object's truth is still found)."""
    return Station(None, None, recording.calibration,
                   recording.station.get("camera", "replay://camera"), "replay://turntable")


def open_station(camera_url=None, turntable_url=None, object=None, calibration=None,
                 seed: int = 0) -> Station:
    """Open the station's devices (see `station_urls`) and settle its calibration.

    calibration : a `Calibration`, a path to a calibration JSON, or None: the simulated
        camera's true pose (a real camera then needs a file).
    """
    camera_url, turntable_url = station_urls(camera_url, turntable_url, object, seed)
    camera = open_camera(camera_url)
    try:
        turntable = open_turntable(turntable_url)
    except BaseException:
        camera.close()
        raise
    try:
        if calibration is None:
            if not is_simulated(camera_url):
                raise CalibrationError(
                    f"{camera_url} needs a calibration: run `scanstation calibrate` and pass "
                    "--calibration FILE"
                )
            calibration = Calibration.from_sim(camera)
        elif not isinstance(calibration, Calibration):
            calibration = Calibration.load(calibration)
    except BaseException:
        camera.close()
        turntable.close()
        raise
    follow_turntable(camera, turntable)
    return Station(camera, turntable, calibration, camera_url, turntable_url)


def true_surface(camera_url: str | None):
    """The simulated camera's true object mesh (table frame at angle 0, mm), else None."""
    if not is_simulated(camera_url):
        return None
    try:
        camera = backend_class("camera", camera_url).from_url(camera_url)
        return camera.true_object_mesh()
    except Exception as exc:  # the truth is a bonus for the report, never a reason to fail
        log.warning("no true surface for %s: %s", camera_url, exc)
        return None
