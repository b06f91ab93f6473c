"""Batch re-processing: rebuild mesh, cloud and report of many recordings, one task each.

`find_recordings` turns files and folders into `Job` s (a scan folder's segments, a lone
``.mcap``, or every recording found under a collection folder). `Reprocessor.run` submits one
task per recording to a `concurrent.futures` executor (local processes, or a Dask cluster:
`capture.executors`) with a bounded number in flight. What travels: the recording's segment
files as bytes and the parameter overrides out, the output files as bytes back — workers need
no shared disk. The task (`reprocess_recording`) is the replay code path (`capture.replay`):
the recorded plan, calibration and update schedule, so with the same seed the mesh is the live
scan's bit for bit. Outputs land atomically per recording in ``OUT/NAME/`` (built beside it,
then renamed into place), with ``reprocess.json``: a fingerprint of the inputs (size, mtime,
SHA-256 of each segment) and the parameters; a later run skips a recording whose fingerprint
matches. A failing recording is reported with its one-line cause; the others go on.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import hashlib
import json
import logging
import os
import re
import shutil
import socket
import tempfile
import time
import uuid
import warnings
from collections import deque
from collections.abc import Callable, Iterable
from pathlib import Path

from reconstruct.io import write_bytes_atomic

from .recording import FIRST_SEGMENT, segment_paths

log = logging.getLogger(__name__)

FORMAT = "scanstation-reprocess/1"
STAMP = "reprocess.json"
#: Files a finished recording's output folder must hold to count as up to date.
REQUIRED = ("mesh.ply", "cloud.ply", "scan.json")


class ReprocessError(RuntimeError):
    """A recording could not be re-processed (the message names the recording and the cause)."""


@dataclasses.dataclass(frozen=True)
class Job:
    """One recording: ``name`` (its output folder's name), ``segments`` (its files, in order)."""

    name: str
    segments: tuple[Path, ...]

    @property
    def source(self) -> Path:
        """What the user named: the scan folder, or the lone recording file."""
        first = self.segments[0]
        return first.parent if first.name == FIRST_SEGMENT else first


@dataclasses.dataclass
class Outcome:
    """How one recording went: ``status`` "ok", "skipped" or "failed"; ``cause`` when failed."""

    job: Job
    status: str
    seconds: float = 0.0
    cause: str = ""
    figures: dict = dataclasses.field(default_factory=dict)


def find_recordings(paths: Iterable) -> list[Job]:
    """Jobs for recording files, scan folders, and folders holding scan folders (searched
    recursively, sorted). Raises `ReprocessError` for a path with no recording, or two
    recordings that would write the same output folder."""
    jobs: list[Job] = []
    for raw in paths:
        path = Path(raw)
        if path.is_file():
            if path.suffix != ".mcap":
                raise ReprocessError(f"{path}: not a recording (.mcap file or scan folder)")
            segments = segment_paths(path.parent) if path.name == FIRST_SEGMENT else [path]
            jobs.append(_job(segments))
        elif path.is_dir():
            found = _scan_folders(path)
            if not found:
                raise ReprocessError(f"{path}: no recording (.mcap) in this folder or below")
            jobs.extend(found)
        else:
            raise ReprocessError(f"{path}: no such file or folder")
    seen: dict[str, Job] = {}
    for job in jobs:
        other = seen.setdefault(job.name, job)
        if other is not job and other.segments != job.segments:
            raise ReprocessError(f"{other.source} and {job.source} would both write "
                                 f"OUT/{job.name}: rename one of them")
    return list({job.name: job for job in jobs}.values())


def _job(segments) -> Job:
    segments = tuple(Path(p) for p in segments)
    first = segments[0]
    return Job(first.parent.name if first.name == FIRST_SEGMENT else first.stem, segments)


def _scan_folders(root: Path) -> list[Job]:
    jobs = []
    for folder, dirs, files in os.walk(root):
        dirs.sort()
        here = Path(folder)
        if FIRST_SEGMENT in files:
            jobs.append(_job(segment_paths(here)))
            dirs.clear()  # a scan folder's sub-folders (engine/) hold no recordings
            continue
        jobs.extend(_job([here / f]) for f in sorted(files) if f.endswith(".mcap")
                    and not f.startswith("."))
    return jobs


# -- fingerprint ---------------------------------------------------------------------------------
def fingerprint(job: Job, overrides: dict, digests: dict[Path, str] | None = None) -> dict:
    """What the outputs depend on: the parameters and each segment (name, size, mtime, SHA-256;
    ``digests``: known SHA-256 by path, else read from disk)."""
    digests = digests or {}
    segments = []
    for path in job.segments:
        stat = path.stat()
        segments.append({"name": path.name, "size": stat.st_size, "mtime_ns": stat.st_mtime_ns,
                         "sha256": digests.get(path) or _sha256(path.read_bytes())})
    return {"format": FORMAT, "params": dict(sorted(overrides.items())), "segments": segments}


def up_to_date(target: Path, job: Job, overrides: dict) -> bool:
    """True when ``target`` holds every output for these parameters and these very inputs (the
    SHA-256 is only recomputed for a segment whose size matches but mtime changed)."""
    try:
        stamp = json.loads((target / STAMP).read_text())
    except (OSError, ValueError):
        return False
    if stamp.get("format") != FORMAT or stamp.get("params") != dict(sorted(overrides.items())):
        return False
    if not all((target / name).is_file() for name in REQUIRED):
        return False
    recorded = stamp.get("segments") or []
    if [s.get("name") for s in recorded] != [p.name for p in job.segments]:
        return False
    for path, known in zip(job.segments, recorded, strict=True):
        stat = path.stat()
        if stat.st_size != known.get("size"):
            return False
        if stat.st_mtime_ns != known.get("mtime_ns") and \
                _sha256(path.read_bytes()) != known.get("sha256"):
            return False
    return True


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


# -- the task (runs on a worker) ------------------------------------------------------------------
#: The replays' temporary folders: ``scanstation-reprocess-<host>-<pid>-…`` in the system's
#: temporary folder. A worker killed mid-replay (SIGKILL, the OOM killer, a cluster's node taken
#: away) cannot remove its own, a copy of the recording; the next replay on the machine removes
#: those of its host whose process is gone (CI's killed-worker test left one at each run). The
#: host in the name keeps a container sharing the folder, whose processes it cannot see, from
#: taking another's for gone.
TEMP_PREFIX = "scanstation-reprocess-"


def _host_prefix() -> str:
    """``scanstation-reprocess-<host>-``: this host's replays' temporary folders' names begin so."""
    return f"{TEMP_PREFIX}{re.sub(r'[^A-Za-z0-9._]', '_', socket.gethostname()) or 'host'}-"


def replay_folder_prefix(pid: int | None = None) -> str:
    """The name a replay's temporary folder starts with, for process ``pid`` (default: this
    one) on this host."""
    return f"{_host_prefix()}{os.getpid() if pid is None else int(pid)}-"


def sweep_stale_folders(parent: Path | None = None) -> int:
    """Remove the replays' temporary folders of this host in ``parent`` (default: the system's
    temporary folder) whose process is gone; returns how many. Only POSIX names a folder's
    process."""
    if os.name != "posix":
        return 0
    parent = Path(tempfile.gettempdir()) if parent is None else Path(parent)
    host = _host_prefix()
    removed = 0
    for folder in parent.glob(f"{host}*-*"):
        pid = folder.name[len(host):].split("-", 1)[0]
        if (not pid.isdigit() or _alive(int(pid)) or folder.is_symlink()
                or not folder.is_dir()):
            continue
        shutil.rmtree(folder, ignore_errors=True)
        removed += not folder.exists()
    if removed:
        log.info("removed %d temporary folder(s) of replays whose process was killed", removed)
    return removed


def _alive(pid: int) -> bool:
    """Whether process ``pid`` exists (one of another user's counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def reprocess_recording(segments: list[tuple[str, bytes]], overrides: dict,
                        source: str = "", target: str = "") -> dict:
    """Replay one recording into a temporary folder; its output files as bytes.

    segments : [(file name, MCAP bytes)] in order.  overrides : e.g. {"lam": 2.0, "seed": 1}.
    source, target : the recording's and the output's paths on the submitting machine (messages
    and scan.json name them instead of the worker's temporary folders).
    Returns {"files": {relative path: bytes}, "seconds", "cpu_seconds" (the worker process's,
    all threads), "figures", "warnings": [one line]}, or {"error": one-line cause, "seconds",
    "cpu_seconds", "warnings"} when the recording cannot be replayed.
    """
    started, cpu = time.perf_counter(), time.process_time()
    sweep_stale_folders()
    with tempfile.TemporaryDirectory(prefix=replay_folder_prefix()) as tmp:
        src, out = Path(tmp) / "in", Path(tmp) / "out"

        def named(text: str) -> str:
            return text.replace(str(out), target or "OUT").replace(str(src), source or "INPUT")

        notes: list[str] = []
        try:
            with _collect_warnings(notes):
                result = _replay(segments, overrides, src, out, named)
        except ReprocessError as exc:
            result = {"error": str(exc)}
        notes = [named(n) for n in notes]
    return {**result, "seconds": time.perf_counter() - started, "warnings": notes,
            "cpu_seconds": time.process_time() - cpu}


def _replay(segments, overrides: dict, src: Path, out: Path, named) -> dict:
    from .replay import replay_runner

    src.mkdir()
    for name, data in segments:
        (src / name).write_bytes(data)
    # a lone file by its own name (a folder's segments are found by theirs)
    source = src / segments[0][0] if len(segments) == 1 else src
    try:
        runner = replay_runner(source, out, workers=1, **overrides)
        state = runner.start().wait()
    except Exception as exc:
        raise ReprocessError(named(_one_line(exc))) from None
    if state != "done":
        raise ReprocessError(named(f"replay {state}: {runner.reason}"))
    engine = runner.engine
    files = {}
    for path in sorted(out.rglob("*")):
        if path.is_file() and not path.name.startswith("."):
            data = path.read_bytes()
            if path.suffix == ".json":
                data = named(data.decode()).encode()
            files[path.relative_to(out).as_posix()] = data
    return {"files": files,
            "figures": {k: engine.figures.get(k) for k in ("faces", "vertices", "points")}}


@contextlib.contextmanager
def _collect_warnings(notes: list):
    """Gather the task's warnings and WARNING log records (of every thread: the replay runs on
    its own) as one-line strings in ``notes``, instead of the worker's stderr."""
    handler = _ListHandler(notes)
    loggers = [logging.getLogger(name) for name in ("capture", "reconstruct")]
    propagate = [logger.propagate for logger in loggers]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for logger in loggers:
            logger.addHandler(handler)
            logger.propagate = False
        try:
            yield notes
        finally:
            for logger, before in zip(loggers, propagate, strict=True):
                logger.removeHandler(handler)
                logger.propagate = before
            notes.extend(f"{w.category.__name__}: {str(w.message).splitlines()[0]}"
                         for w in caught)


class _ListHandler(logging.Handler):
    def __init__(self, notes: list):
        super().__init__(logging.WARNING)
        self.notes = notes

    def emit(self, record: logging.LogRecord) -> None:
        self.notes.append(record.getMessage().splitlines()[0])


def _one_line(exc: BaseException) -> str:
    lines = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {lines[0] if lines else ''}".rstrip(": ")


# -- outputs ------------------------------------------------------------------------------------
def write_outputs(target: Path, files: dict[str, bytes], stamp: dict) -> Path:
    """Write ``files`` and the stamp into a new folder beside ``target``, then swap it into
    place: a reader sees the old folder or the new one, never a mix."""
    target.parent.mkdir(parents=True, exist_ok=True)
    partial = target.parent / f".{target.name}.partial-{uuid.uuid4().hex[:8]}"
    partial.mkdir()
    try:
        for name, data in files.items():
            path = partial / name
            path.parent.mkdir(parents=True, exist_ok=True)
            write_bytes_atomic(path, data)
        write_bytes_atomic(partial / STAMP, json.dumps(stamp, indent=1).encode())
        old = None
        if target.exists():
            old = target.parent / f".{target.name}.old-{uuid.uuid4().hex[:8]}"
            os.replace(target, old)
        os.replace(partial, target)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
    return target


# -- the batch ------------------------------------------------------------------------------------
class Reprocessor:
    """Re-process jobs into ``out_dir`` on ``executor`` (None: one after the other, here).

    overrides : reconstruction parameters (lam, depth, seed).  force : redo up-to-date ones.
    in_flight : tasks submitted at once (bounds the recordings held in memory; default twice
    the executor's workers).  on_outcome : callable(outcome, done, total) after each one.
    """

    def __init__(self, out_dir, overrides: dict | None = None, executor=None,
                 force: bool = False, in_flight: int | None = None,
                 on_outcome: Callable[[Outcome, int, int], None] | None = None):
        self.out_dir = Path(out_dir)
        self.overrides = dict(overrides or {})
        self.executor = executor
        self.force = force
        workers = getattr(executor, "n_workers", None) or getattr(executor, "_max_workers", 1)
        self.in_flight = max(1, in_flight or 2 * workers)
        self.on_outcome = on_outcome

    def run(self, jobs: list[Job]) -> list[Outcome]:
        """Every job's outcome, in the jobs' order."""
        outcomes: dict[str, Outcome] = {}
        total, done = len(jobs), 0

        def record(outcome: Outcome) -> None:
            nonlocal done
            outcomes[outcome.job.name] = outcome
            done += 1
            if self.on_outcome is not None:
                self.on_outcome(outcome, done, total)

        queue = deque()
        for job in jobs:
            try:
                fresh = not self.force and up_to_date(self.out_dir / job.name, job,
                                                      self.overrides)
            except OSError as exc:
                record(Outcome(job, "failed", cause=f"{job.source}: {exc.strerror or exc}"))
                continue
            if fresh:
                record(Outcome(job, "skipped", cause="up to date"))
            else:
                queue.append(job)
        running: dict[concurrent.futures.Future, tuple[Job, dict, float]] = {}
        while queue or running:
            while queue and len(running) < self.in_flight:
                job = queue.popleft()
                try:
                    started = time.perf_counter()
                    future, stamp = self._submit(job)
                    running[future] = (job, stamp, started)
                except Exception as exc:
                    record(Outcome(job, "failed", cause=_one_line(exc)))
            if not running:
                continue
            finished, _ = concurrent.futures.wait(
                running, return_when=concurrent.futures.FIRST_COMPLETED)
            for future in finished:
                job, stamp, started = running.pop(future)
                record(self._collect(job, future, stamp, started))
        return [outcomes[job.name] for job in jobs]

    def _submit(self, job: Job) -> tuple[concurrent.futures.Future, dict]:
        """(the task's future, the job's fingerprint): reads the segments once for both."""
        segments = []
        digests = {}
        for path in job.segments:
            try:
                data = path.read_bytes()
            except OSError as exc:
                raise ReprocessError(f"{path}: {exc.strerror or exc}") from exc
            digests[path] = _sha256(data)
            segments.append((path.name, data))
        stamp = fingerprint(job, self.overrides, digests)
        args = (segments, self.overrides, str(job.source), str(self.out_dir / job.name))
        if self.executor is None:
            future: concurrent.futures.Future = concurrent.futures.Future()
            try:
                future.set_result(reprocess_recording(*args))
            except Exception as exc:
                future.set_exception(exc)
            return future, stamp
        return self.executor.submit(reprocess_recording, *args), stamp

    def _collect(self, job: Job, future, stamp: dict, started: float) -> Outcome:
        seconds = time.perf_counter() - started
        try:
            result = future.result()
        except Exception as exc:  # KilledWorker (lost 3 times), a lost cluster, a bug
            log.warning("%s failed: %s", job.source, _one_line(exc))
            return Outcome(job, "failed", seconds, _one_line(exc))
        for note in result["warnings"]:
            log.debug("%s: %s", job.name, note)
        if "error" in result:
            log.warning("%s failed: %s", job.source, result["error"])
            return Outcome(job, "failed", result["seconds"], result["error"])
        stamp = {**stamp, "written": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                 "task_seconds": round(result["seconds"], 3)}
        try:
            write_outputs(self.out_dir / job.name, result["files"], stamp)
        except OSError as exc:
            return Outcome(job, "failed", seconds,
                           f"writing {self.out_dir / job.name}: {exc.strerror or exc}")
        return Outcome(job, "ok", result["seconds"],
                       figures={**result["figures"], "cpu_seconds": result["cpu_seconds"]})
