"""The daemon under load, and its recovery from SIGKILL — a real `scanstation serve` process on
loopback, driven by this one (asyncio + httpx, so the load generator has its own interpreter).

    OMP_NUM_THREADS=1 .venv/bin/python -m bench.daemon_load [--seconds 30] [--pollers 50]
        [--watchers 20] [--interval 0.1] [--kill-after 5]

Load: ``pollers`` clients each GET the scan's status every ``interval`` s (one request at a
time; each client's first request, which sets up its connection, is not counted) while
``watchers`` clients hold its SSE event stream, for ``seconds`` s — first with the
scan paused (the peer: same connections, no capture or reconstruction running), then with the
default simulated scan (36 views, 3 frames, full reconstruction) running. Reported: requests,
errors, status latency p50 / p99 / max, documents each watcher received (all must agree with
the scan's history). Target: status p99 <= 100 ms during the scan.

Hung device: first, a scan is started against a turntable that never answers (a loopback
listener that accepts and stays silent, ``socket://…?timeout=30``, the longest timeout the
daemon allows) and the pollers GET its status for ``seconds`` s while its process waits on the
device. Reported: the POST's own time, status p50 / p99 / max, the scan's state (``starting``
throughout), and how it ends when cancelled. Target: status p99 <= 100 ms, POST in ms.

Recovery: a second scan is SIGKILLed with the daemon after ``kill-after`` views; the daemon is
restarted on the same state dir; reported: views done at the kill, recovered from the recording
and replayed from it (capture and processing), restart time until /healthz answers (peer: the
first start), the state then, and the time for resume to finish the scan.
"""

from __future__ import annotations

import argparse
import asyncio
import functools
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

from capture.recording import read_recording
from capture.replay import replay_plan
from capture.runner import ScanRunner


class Daemon:
    def __init__(self, state_dir: Path, port: int, log: Path):
        self.url = f"http://127.0.0.1:{port}"
        started = time.perf_counter()
        self.process = subprocess.Popen(
            [sys.executable, "-m", "capture.cli", "-q", "serve", "--port", str(port),
             "--state-dir", str(state_dir)], stdout=open(log, "ab"), stderr=subprocess.STDOUT)
        while True:
            if self.process.poll() is not None:
                raise RuntimeError(f"the daemon exited; see {log}")
            try:
                if httpx.get(f"{self.url}/healthz", timeout=1).status_code == 200:
                    break
            except httpx.TransportError:
                time.sleep(0.02)
        self.start_s = time.perf_counter() - started

    def api(self, method: str, path: str, **kwargs) -> dict:
        answer = httpx.request(method, f"{self.url}/api/v1{path}", timeout=30, **kwargs)
        answer.raise_for_status()
        return answer.json()

    def wait(self, scan_id: str, predicate, timeout: float = 900.0) -> dict:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            scan = self.api("GET", f"/scans/{scan_id}")
            if predicate(scan):
                return scan
            time.sleep(0.05)
        raise TimeoutError(f"scan {scan_id}: condition not reached in {timeout:g} s")

    def kill(self, sig=signal.SIGKILL) -> None:
        self.process.send_signal(sig)
        self.process.wait(60)


# -- load ----------------------------------------------------------------------------------------
async def poller(url: str, interval: float, go: asyncio.Event, stop: asyncio.Event,
                 warm: list, record: list, errors: list):
    """GET ``url`` every ``interval`` s from ``go`` to ``stop``; the first GET (connection
    set-up) happens before ``go`` and is not counted."""
    async with httpx.AsyncClient(timeout=10) as client:
        await client.get(url)
        warm.append(1)
        await go.wait()
        while not stop.is_set():
            started = time.perf_counter()
            try:
                answer = await client.get(url)
                answer.raise_for_status()
                record.append(time.perf_counter() - started)
            except httpx.HTTPError as exc:
                errors.append(repr(exc))
            await asyncio.sleep(max(0.0, interval - (time.perf_counter() - started)))


async def watcher(url: str, counts: dict, key: int, errors: list):
    """Hold the SSE stream until the server ends it; count documents (by phase)."""
    try:
        async with httpx.AsyncClient(timeout=httpx.Timeout(10, read=None)) as client, \
                client.stream("GET", url) as answer:
            answer.raise_for_status()
            async for line in answer.aiter_lines():
                if line.startswith("data: "):
                    counts[key] = counts.get(key, 0) + 1
    except httpx.HTTPError as exc:
        errors.append(repr(exc))


async def load_phase(daemon: Daemon, scan_id: str, args, watchers_counts, before_start=None):
    """Run the pollers for ``args.seconds``; returns (latencies s, errors)."""
    status = f"{daemon.url}/api/v1/scans/{scan_id}"
    go, stop, warm, latencies, errors = asyncio.Event(), asyncio.Event(), [], [], []
    tasks = [asyncio.create_task(poller(status, args.interval, go, stop, warm, latencies,
                                        errors)) for _ in range(args.pollers)]
    while len(warm) < args.pollers:
        await asyncio.sleep(0.05)
    if before_start is not None:
        await asyncio.to_thread(before_start)
    go.set()
    await asyncio.sleep(args.seconds)
    stop.set()
    await asyncio.gather(*tasks)
    return np.array(latencies), errors


async def run_load(daemon: Daemon, args) -> list[dict]:
    scan = daemon.api("POST", "/scans", json={})  # the default simulated scan
    scan_id = scan["id"]
    daemon.wait(scan_id, lambda s: s["state"] == "running")  # POST answers while `starting`
    daemon.api("POST", f"/scans/{scan_id}/pause")
    daemon.wait(scan_id, lambda s: s["state"] == "paused")
    events = f"{daemon.url}/api/v1/scans/{scan_id}/events"
    counts: list[dict] = [{} for _ in range(args.watchers)]
    sse_errors: list = []
    watchers = [asyncio.create_task(watcher(events, counts[i], 0, sse_errors))
                for i in range(args.watchers)]
    rows = []
    for phase, action in (("paused scan (peer)", None), ("scan running", "resume")):
        before = [dict(c) for c in counts]
        start = functools.partial(daemon.api, "POST", f"/scans/{scan_id}/{action}") \
            if action else None
        latencies, errors = await load_phase(daemon, scan_id, args, counts, start)
        progress = daemon.api("GET", f"/scans/{scan_id}")["progress"]
        received = [c.get(0, 0) - b.get(0, 0) for c, b in zip(counts, before, strict=True)]
        rows.append({"phase": phase, "requests": len(latencies) + len(errors),
                     "errors": len(errors), "p50": np.percentile(latencies, 50) * 1e3,
                     "p99": np.percentile(latencies, 99) * 1e3, "max": latencies.max() * 1e3,
                     "docs": (min(received), max(received)), "views": progress["views_done"]})
    daemon.api("POST", f"/scans/{scan_id}/cancel")
    await asyncio.wait_for(asyncio.gather(*watchers), 120)
    text = httpx.get(events, timeout=30).text
    history = sum(line.startswith("data: ") for line in text.splitlines())
    totals = {c.get(0, 0) for c in counts}
    rows.append({"sse_errors": len(sse_errors), "totals": sorted(totals), "history": history})
    return rows


async def run_hung_device(daemon: Daemon, args) -> dict:
    """A scan whose turntable never answers: the API must not wait on it."""
    import socket

    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        url = f"socket://127.0.0.1:{listener.getsockname()[1]}?timeout=30"
        started = time.perf_counter()
        scan = daemon.api("POST", "/scans", json={"turntable_url": url})
        post_ms = (time.perf_counter() - started) * 1e3
        latencies, errors = await load_phase(daemon, scan["id"], args, None)
        during = daemon.api("GET", f"/scans/{scan['id']}")["state"]
        daemon.api("POST", f"/scans/{scan['id']}/cancel")
        ended = daemon.wait(scan["id"], lambda s: s["state"] in ("interrupted", "failed"), 60)
    return {"phase": "device never answers", "requests": len(latencies) + len(errors),
            "errors": len(errors), "p50": np.percentile(latencies, 50) * 1e3,
            "p99": np.percentile(latencies, 99) * 1e3, "max": latencies.max() * 1e3,
            "post_ms": post_ms, "first_state": scan["state"], "during": during,
            "ended": f"{ended['state']} ({ended['reason']})"}


# -- recovery ------------------------------------------------------------------------------------
def replayed_views(folder: Path, out_dir: Path) -> tuple[str, int]:
    """Replay a (torn) recording through the runner, capture and processing only: (final
    state, views replayed)."""
    import dataclasses

    recording = read_recording(folder)
    plan = dataclasses.replace(replay_plan(recording), reconstruction=None)
    runner = ScanRunner(plan, out_dir=out_dir, replay=recording, record=False)
    state = runner.start().wait()
    return state, sum(d.kind == "view" for d in runner.documents)


def run_kill(state_dir: Path, port: int, log: Path, kill_after: int, first_start_s: float):
    daemon = Daemon(state_dir, port, log)
    scan_id = daemon.api("POST", "/scans", json={})["id"]
    seen = daemon.wait(scan_id, lambda s: s["progress"]["views_done"] >= kill_after)
    seen_views = seen["progress"]["views_done"]
    daemon.kill(signal.SIGKILL)
    folder = state_dir / "scans" / scan_id
    recorded = len(read_recording(folder).views)
    replay_state, replayed = replayed_views(folder, state_dir.parent / "replay-after-kill")
    restarted = Daemon(state_dir, port, log)
    after = restarted.api("GET", f"/scans/{scan_id}")
    started = time.perf_counter()
    while True:  # 409 while the killed daemon's scan process still stops (one step at most)
        answer = httpx.post(f"{restarted.url}/api/v1/scans/{scan_id}/resume", timeout=30)
        if answer.status_code != 409 or time.perf_counter() - started > 120:
            answer.raise_for_status()
            break
        time.sleep(0.2)
    done = restarted.wait(scan_id, lambda s: s["state"] in ("done", "failed"))
    resume_s = time.perf_counter() - started
    views = sorted(v.index for v in read_recording(folder).views)
    restarted.kill(signal.SIGTERM)
    return {"seen": seen_views, "recorded": recorded, "replayed": replayed,
            "replay_state": replay_state, "restart_s": restarted.start_s,
            "first_start_s": first_start_s, "state_after": after["state"],
            "resume_s": resume_s, "final": done["state"], "views": len(set(views)),
            "total": done["progress"]["views_total"], "segments": done["files"][
                "recording_segments"], "mesh": done["files"]["mesh"]}


def free_port() -> int:
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--pollers", type=int, default=50)
    parser.add_argument("--watchers", type=int, default=20)
    parser.add_argument("--interval", type=float, default=0.1, help="s between a poller's GETs")
    parser.add_argument("--kill-after", type=int, default=5, help="views before the SIGKILL")
    parser.add_argument("--no-kill", action="store_true", help="load figures only")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="daemon-bench-") as tmp:
        state_dir, log, port = Path(tmp) / "state", Path(tmp) / "daemon.log", free_port()
        daemon = Daemon(state_dir, port, log)
        try:
            hung = asyncio.run(run_hung_device(daemon, args))
            rows = asyncio.run(run_load(daemon, args))
        finally:
            daemon.kill(signal.SIGTERM)
        kill = None if args.no_kill else run_kill(
            Path(tmp) / "state-kill", free_port(), log, args.kill_after, daemon.start_s)

    print(f"\ndaemon load: {args.pollers} status pollers (one GET every {args.interval:g} s "
          f"each) + {args.watchers} SSE watchers, {args.seconds:g} s per phase, loopback, "
          f"{os.cpu_count()} cores")
    print(f"{'phase':<20} {'requests':>8} {'errors':>6} {'p50 ms':>7} {'p99 ms':>7} "
          f"{'max ms':>7} {'docs/watcher':>13} {'views at end':>12}")
    print(f"{hung['phase']:<20} {hung['requests']:>8} {hung['errors']:>6} {hung['p50']:>7.1f} "
          f"{hung['p99']:>7.1f} {hung['max']:>7.1f} {'-':>13} {'-':>12}")
    for row in rows[:2]:
        docs = "{}..{}".format(*row["docs"])
        print(f"{row['phase']:<20} {row['requests']:>8} {row['errors']:>6} {row['p50']:>7.1f} "
              f"{row['p99']:>7.1f} {row['max']:>7.1f} {docs:>13} {row['views']:>12}")
    peer, scan = rows[0], rows[1]
    print(f"ratio running / paused: p50 x{scan['p50'] / peer['p50']:.2f}, "
          f"p99 x{scan['p99'] / peer['p99']:.2f}")
    print(f"SSE: {rows[2]['sse_errors']} errors; documents per watcher over the whole stream: "
          f"{rows[2]['totals']}; the scan's history holds {rows[2]['history']}")
    sse = rows[2]
    consistent = sse["sse_errors"] == 0 and sse["totals"] == [sse["history"]]
    verdict = "met" if scan["p99"] <= 100 and scan["errors"] == 0 and consistent else "NOT met"
    print(f"target status p99 <= 100 ms, no errors, every watcher got the whole history: "
          f"{verdict}")
    print(f"device never answers: POST answered in {hung['post_ms']:.1f} ms "
          f"({hung['first_state']}), the scan was {hung['during']} after {args.seconds:g} s, "
          f"cancel -> {hung['ended']}")
    ok = hung["p99"] <= 100 and hung["errors"] == 0 and hung["during"] == "starting"
    print(f"target status p99 <= 100 ms while a scan waits on a silent device: "
          f"{'met' if ok else 'NOT met'}")
    if kill is None:
        return
    print("\nSIGKILL mid-scan, restart, resume (default simulated scan)")
    print(f"  views done when killed {kill['seen']}, recovered from the recording "
          f"{kill['recorded']}, replayed from it {kill['replayed']} ({kill['replay_state']})")
    print(f"  restart until /healthz {kill['restart_s']:.2f} s (first start "
          f"{kill['first_start_s']:.2f} s); state after restart: {kill['state_after']}")
    print(f"  resume -> {kill['final']} in {kill['resume_s']:.1f} s: {kill['views']}/"
          f"{kill['total']} views in {kill['segments']} recording segments, mesh "
          f"{'written' if kill['mesh'] else 'missing'}")
    ok = (kill["recorded"] >= kill["seen"] and kill["replayed"] == kill["recorded"]
          and kill["state_after"] == "interrupted" and kill["final"] == "done"
          and kill["views"] == kill["total"] and kill["mesh"])
    print(f"target interrupted after restart, every completed view replayed, resume finishes: "
          f"{'met' if ok else 'NOT met'}")


if __name__ == "__main__":
    main()
