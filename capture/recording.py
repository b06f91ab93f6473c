"""Recording a scan to MCAP, and reading it back — also from a file a crash cut short.

Layout (opens in Foxglove): a metadata record ``scanstation`` with the plan, calibration and
station; topic ``/scan/documents`` with every document as JSON; topic ``/camera/depth`` with
each raw frame as a JSON ``foxglove.RawImage`` (``16UC1``, little-endian, base64) plus its view
index and table angle. Chunks are zstd-compressed (the mcap package's own dependency). Each
view's frames and its view document go into one chunk that is ended, flushed and fsynced when
the view completes, so a SIGKILL loses at most the view in progress: a file without its footer
is read with the non-seeking record stream, every complete chunk is recovered.

A resumed scan appends a new segment (``recording-2.mcap``, …) next to ``recording.mcap``; the
old segments are never rewritten. `read_recording` of a directory joins the segments in order.
"""

from __future__ import annotations

import base64
import dataclasses
import json
import logging
import os
import re
import struct
import time
from pathlib import Path

import numpy as np
from mcap.exceptions import McapError
from mcap.records import Channel, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer
from zstandard import ZstdError

from .calibration import Calibration
from .documents import Document, StartDocument, StopDocument, ViewDocument
from .plan import ScanPlan

log = logging.getLogger(__name__)

FORMAT = "scanstation-recording/1"
DOCUMENTS_TOPIC = "/scan/documents"
DEPTH_TOPIC = "/camera/depth"
FIRST_SEGMENT = "recording.mcap"
_SEGMENT = re.compile(r"^recording(?:-(\d+))?\.mcap$")
_RAW_IMAGE_SCHEMA = {
    "title": "foxglove.RawImage",
    "type": "object",
    "properties": {
        "timestamp": {"type": "object", "properties": {"sec": {"type": "integer"},
                                                       "nsec": {"type": "integer"}}},
        "frame_id": {"type": "string"},
        "width": {"type": "integer"},
        "height": {"type": "integer"},
        "encoding": {"type": "string"},
        "step": {"type": "integer"},
        "data": {"type": "string", "contentEncoding": "base64"},
    },
}


class RecordingError(ValueError):
    """A recording that cannot be read or written (the message names the file and the cause)."""


def segment_paths(directory) -> list[Path]:
    """The recording segments in ``directory``, in order (recording.mcap, recording-2.mcap…)."""
    found = []
    for path in Path(directory).iterdir():
        match = _SEGMENT.match(path.name)
        if match and path.is_file():
            found.append((int(match.group(1) or 1), path))
    return [p for _, p in sorted(found)]


def next_segment(directory) -> tuple[int, Path]:
    """(number, path) of the segment a new recording in ``directory`` should write."""
    existing = segment_paths(directory) if Path(directory).is_dir() else []
    if not existing:
        return 1, Path(directory) / FIRST_SEGMENT
    number = int(_SEGMENT.match(existing[-1].name).group(1) or 1) + 1
    return number, Path(directory) / f"recording-{number}.mcap"


def _stamp(seconds: float) -> dict:
    ns = int(round(seconds * 1e9))
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


class RecordingWriter:
    """A document subscriber writing one MCAP segment. Call it with each document.

    path : the segment file (created; must not exist).  The metadata record is written and
    synced by `open()`, before the scan moves anything.
    """

    def __init__(self, path, plan: ScanPlan, calibration: Calibration, station: dict,
                 scan_id: str, segment: int = 1):
        self.path = Path(path)
        self.plan, self.calibration, self.station = plan, calibration, station
        self.scan_id, self.segment = scan_id, segment
        self._file = None
        self._writer: Writer | None = None

    def open(self) -> RecordingWriter:
        self._file = open(self.path, "xb")  # noqa: SIM115 - closed in close()
        writer = Writer(self._file, chunk_size=1 << 30, compression=CompressionType.ZSTD)
        writer.start(profile="", library="scanstation")
        document_schema = writer.register_schema(
            "scanstation.Document", "jsonschema", json.dumps({"type": "object"}).encode())
        image_schema = writer.register_schema(
            "foxglove.RawImage", "jsonschema", json.dumps(_RAW_IMAGE_SCHEMA).encode())
        self._documents = writer.register_channel(DOCUMENTS_TOPIC, "json", document_schema)
        self._depth = writer.register_channel(DEPTH_TOPIC, "json", image_schema)
        writer.add_metadata("scanstation", {
            "format": FORMAT,
            "scan_id": self.scan_id,
            "segment": str(self.segment),
            "plan": self.plan.to_json(),
            "calibration": self.calibration.to_json(),
            "station": json.dumps(self.station),
        })
        self._writer = writer
        self._sync()
        return self

    def __call__(self, document: Document) -> None:
        if self._writer is None:
            return
        now = time.time_ns()
        if isinstance(document, ViewDocument):
            for j, (depth, stamp) in enumerate(zip(document.frames, document.timestamps,
                                                   strict=True)):
                self._add(self._depth, now, self._depth_message(document, j, depth, stamp))
        self._add(self._documents, now, document.to_dict())
        if isinstance(document, (ViewDocument, StartDocument)):
            self._sync()
        elif isinstance(document, StopDocument):
            self.close()

    def _depth_message(self, view: ViewDocument, j: int, depth, stamp: float) -> dict:
        depth = np.ascontiguousarray(depth, dtype="<u2")
        return {
            "timestamp": _stamp(stamp),
            "frame_id": "camera",
            "width": int(depth.shape[1]),
            "height": int(depth.shape[0]),
            "encoding": "16UC1",
            "step": int(2 * depth.shape[1]),
            "data": base64.b64encode(depth.tobytes()).decode("ascii"),
            "view": view.index,
            "frame": j,
            "angle_deg": view.angle_deg,
        }

    def _add(self, channel: int, now: int, payload: dict) -> None:
        data = json.dumps(payload, separators=(",", ":")).encode()
        self._writer.add_message(channel, log_time=now, data=data, publish_time=now)

    def _sync(self) -> None:
        """End the chunk, push it to the file and to the disk."""
        self._writer.flush()
        os.fsync(self._file.fileno())

    def close(self) -> None:
        """Write the summary and footer; safe to repeat."""
        writer, self._writer = self._writer, None
        if writer is not None:
            try:
                writer.finish()
                self._file.flush()
                os.fsync(self._file.fileno())
            finally:
                self._file.close()


@dataclasses.dataclass
class RecordedView:
    """One complete view: raw frames (H, W) uint16 mm with their timestamps (s)."""

    index: int
    angle_deg: float
    measured_angle_deg: float
    frames: list
    timestamps: tuple


@dataclasses.dataclass
class Recording:
    """What a recording holds. ``complete``: every segment ended with its footer."""

    plan: ScanPlan
    calibration: Calibration
    station: dict
    scan_id: str
    views: list
    documents: list
    segments: list
    complete: bool

    @property
    def angles(self) -> list[float]:
        return [v.angle_deg for v in self.views]


def _read_segment(path: Path):
    """(metadata dict, documents, frames {(view, frame): (depth, stamp)}, read to the end)."""
    meta, documents, frames, channels, footer = None, [], {}, {}, False
    try:
        with open(path, "rb") as handle:
            for record in StreamReader(handle, validate_crcs=True).records:
                if isinstance(record, Metadata) and record.name == "scanstation":
                    meta = dict(record.metadata)
                elif isinstance(record, Channel):
                    channels[record.id] = record.topic
                elif isinstance(record, Message):
                    payload = json.loads(record.data)
                    topic = channels.get(record.channel_id)
                    if topic == DOCUMENTS_TOPIC:
                        documents.append(payload)
                    elif topic == DEPTH_TOPIC:
                        raw = base64.b64decode(payload["data"])
                        shape = (payload["height"], payload["width"])
                        depth = np.frombuffer(raw, dtype="<u2").reshape(shape).astype(np.uint16)
                        stamp = payload["timestamp"]["sec"] + payload["timestamp"]["nsec"] * 1e-9
                        frames[(payload["view"], payload["frame"])] = (depth, stamp)
                elif isinstance(record, (Schema,)):
                    continue
                elif isinstance(record, Footer):
                    footer = True
    except (McapError, ValueError, KeyError, EOFError, struct.error, ZstdError) as exc:
        # A crash leaves a torn last chunk (or no footer), a bad disk a damaged one (its zstd
        # data does not decompress): keep everything before it.
        footer = False
        log.log(logging.INFO if meta is not None else logging.DEBUG,  # (none: its error says)
                "%s: stopped reading at a torn or damaged record (%s): recovered what came "
                "before", path, type(exc).__name__)
    except OSError as exc:
        raise RecordingError(f"cannot read recording {path}: {exc.strerror or exc}") from exc
    return meta, documents, frames, footer


def read_recording(path) -> Recording:
    """Read a recording file, or every segment of a scan directory, recovering torn files."""
    path = Path(path)
    if path.is_dir():
        segments = segment_paths(path)
        if not segments:
            raise RecordingError(f"{path}: no recording.mcap in this directory")
    elif path.is_file():
        segments = [path]
    else:
        raise RecordingError(f"{path}: no such recording")
    first, views, documents, complete = None, [], [], True
    for segment in segments:
        meta, docs, frames, footer = _read_segment(segment)
        if meta is None or meta.get("format") != FORMAT:
            raise RecordingError(f"{segment}: not a ScanStation recording (no scan metadata)")
        first = first or meta
        if meta.get("scan_id") != first.get("scan_id"):
            raise RecordingError(f"{segment}: a segment of another scan (scan id "
                                 f"{meta.get('scan_id')}, not {first.get('scan_id')})")
        complete &= footer
        documents += docs
        for doc in docs:
            if doc.get("kind") != "view":
                continue
            i, n = doc["index"], doc["n_frames"]
            got = [frames.get((i, j)) for j in range(n)]
            if any(g is None for g in got):
                continue  # frames torn off: the view was not complete
            views.append(RecordedView(i, float(doc["angle_deg"]), float(doc["measured_angle_deg"]),
                                      [g[0] for g in got], tuple(g[1] for g in got)))
    return Recording(
        plan=ScanPlan.from_json(first["plan"]),
        calibration=Calibration.from_json(first["calibration"]),
        station=json.loads(first.get("station", "{}")),
        scan_id=first.get("scan_id", ""),
        views=views,
        documents=documents,
        segments=segments,
        complete=complete,
    )
