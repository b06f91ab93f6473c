"""The document stream of a scan (bluesky's start / event / stop, for a turntable scan).

Every document is a frozen dataclass with a ``kind`` and `to_dict()` giving a JSON-safe dict
(``{"kind": ..., "seq": n, "time": unix s, ...}``). Order within one scan:
``start``, then per view ``view`` and ``progress``, ``mesh`` whenever the engine has a new mesh,
``paused`` / ``resumed`` around a pause (a lost device, or `pause()`), ``error`` for a failure
that ends the scan, and ``stop`` last with the final state and its reason.

A `ViewDocument` also carries the raw frames (``frames``, not part of `to_dict`): the recording
subscriber writes them; other subscribers see counts and timestamps only.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, ClassVar

import numpy as np


def _json_safe(value):
    """Numbers, strings, lists and dicts only; numpy scalars/arrays become Python values."""
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return _json_safe(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


@dataclasses.dataclass(frozen=True)
class Document:
    """Base: ``seq`` numbers documents within a scan from 0, ``time`` is unix seconds."""

    kind: ClassVar[str] = "document"
    seq: int
    time: float

    def to_dict(self) -> dict[str, Any]:
        data = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                if f.metadata.get("json", True)}
        return {"kind": self.kind, **_json_safe(data)}


@dataclasses.dataclass(frozen=True)
class StartDocument(Document):
    """A scan (or a resumed segment of one) begins. ``plan`` and ``calibration`` are their JSON
    dicts; ``station`` names the devices; ``resumed_views`` counts views taken over from an
    earlier recording."""

    kind: ClassVar[str] = "start"
    scan_id: str
    plan: dict
    calibration: dict
    station: dict
    segment: int = 1
    resumed_views: int = 0


@dataclasses.dataclass(frozen=True)
class ViewDocument(Document):
    """One view captured: table angle (degrees, as commanded and as read back), frame count,
    valid pixels of the combined depth, frame timestamps (device seconds). ``frames``: the raw
    (H, W) uint16 mm depth images (the recording writes them before the view is processed)."""

    kind: ClassVar[str] = "view"
    index: int
    angle_deg: float
    measured_angle_deg: float
    n_frames: int
    valid_pixels: int
    timestamps: tuple[float, ...]
    frames: tuple = dataclasses.field(default=(), repr=False, metadata={"json": False})


@dataclasses.dataclass(frozen=True)
class ProgressDocument(Document):
    """After each view: views recorded (this scan, all segments), points the view added after
    processing, points of the merged cloud, seconds since start, and the limits of view the
    object reaches in it ("image edge", "wall", "roof": `ViewProcessor.limits`)."""

    kind: ClassVar[str] = "progress"
    views_done: int
    views_total: int
    view_points: int
    cloud_points: int
    elapsed_s: float
    view_limits: tuple[str, ...] = ()

    @property
    def fraction(self) -> float:
        return self.views_done / max(self.views_total, 1)

    def to_dict(self) -> dict[str, Any]:
        return {**super().to_dict(), "fraction": self.fraction}


@dataclasses.dataclass(frozen=True)
class MeshDocument(Document):
    """The engine has a new mesh (version counts from 1). ``figures``: vertices, faces, points,
    coverage, seconds, patches refit / warm-started / reused, and quality when known."""

    kind: ClassVar[str] = "mesh"
    version: int
    views: int
    final: bool
    figures: dict


@dataclasses.dataclass(frozen=True)
class PausedDocument(Document):
    """The scan paused: ``reason`` is "user" or "device"; ``message`` says what happened."""

    kind: ClassVar[str] = "paused"
    reason: str
    message: str
    view_index: int


@dataclasses.dataclass(frozen=True)
class ResumedDocument(Document):
    kind: ClassVar[str] = "resumed"
    message: str
    view_index: int


@dataclasses.dataclass(frozen=True)
class ErrorDocument(Document):
    """A failure (one line) that ends the scan; ``error`` is the exception's class name."""

    kind: ClassVar[str] = "error"
    error: str
    message: str


@dataclasses.dataclass(frozen=True)
class StopDocument(Document):
    """Last document: final ``state`` (done / failed / interrupted), ``reason`` in words,
    views recorded in this segment and in all, and the files written."""

    kind: ClassVar[str] = "stop"
    state: str
    reason: str
    views_done: int
    views_total: int
    files: dict


KINDS: dict[str, type[Document]] = {
    cls.kind: cls
    for cls in (StartDocument, ViewDocument, ProgressDocument, MeshDocument, PausedDocument,
                ResumedDocument, ErrorDocument, StopDocument)
}


def from_dict(data: dict) -> Document:
    """Rebuild a document from `to_dict` output (a view comes back without its frames)."""
    cls = KINDS.get(data.get("kind"))
    if cls is None:
        raise ValueError(f"unknown document kind {data.get('kind')!r}")
    names = {f.name for f in dataclasses.fields(cls) if f.metadata.get("json", True)}
    values = {k: v for k, v in data.items() if k in names}
    if cls is ViewDocument:
        values["timestamps"] = tuple(values.get("timestamps", ()))
    if cls is ProgressDocument:
        values["view_limits"] = tuple(values.get("view_limits", ()))
    return cls(**values)


def subscribe(lock, subscribers: list, callback):
    """Append ``callback`` to ``subscribers`` under ``lock``; returns its unsubscribe()."""
    with lock:
        subscribers.append(callback)

    def unsubscribe():
        with lock:
            if callback in subscribers:
                subscribers.remove(callback)

    return unsubscribe
