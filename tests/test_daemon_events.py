"""Live events: thread → asyncio fan-out, history and Last-Event-ID, many SSE clients at once."""

from __future__ import annotations

import asyncio
import json
import threading

import httpx
from daemon_helpers import LiveServer, capture_plan, station_urls, wait_for_state
from fastapi.testclient import TestClient

from capture.daemon.app import create_app
from capture.daemon.events import EventChannel, sse_message


async def collect(channel: EventChannel, after: int = 0, limit: int | None = None) -> list:
    items = []
    async for item in channel.stream(after):
        items.append(item)
        if limit is not None and len(items) == limit:
            break
    return items


def test_documents_from_a_thread_reach_every_subscriber_in_order():
    channel = EventChannel()

    async def main():
        readers = [asyncio.create_task(collect(channel)) for _ in range(5)]
        await asyncio.sleep(0.01)
        assert channel.n_subscribers == 5

        def produce():
            for i in range(200):
                channel.publish({"kind": "progress", "views_done": i})
            channel.close()

        producer = threading.Thread(target=produce)
        producer.start()
        results = await asyncio.gather(*readers)
        producer.join()
        return results

    results = asyncio.run(main())
    expected = [(i + 1, {"kind": "progress", "views_done": i}) for i in range(200)]
    assert all(result == expected for result in results)
    assert channel.n_subscribers == 0


def test_late_subscribers_get_the_history_and_after_skips_it():
    channel = EventChannel(max_history=5)
    for i in range(8):
        channel.publish({"n": i})
    channel.close()
    assert [doc["n"] for _, doc in asyncio.run(collect(channel))] == [3, 4, 5, 6, 7]
    assert [i for i, _ in asyncio.run(collect(channel, after=6))] == [7, 8]
    channel.reopen()  # open again (a resumed scan): streams wait for what comes next
    channel.publish({"n": 8})

    async def next_after_9():
        reader = asyncio.create_task(collect(channel, after=9, limit=1))
        await asyncio.sleep(0.01)
        channel.publish({"n": 9})
        return await reader

    assert asyncio.run(next_after_9()) == [(10, {"n": 9})]


def test_a_subscriber_too_slow_for_its_queue_is_dropped_and_catches_up_later():
    channel = EventChannel(queue_size=4)

    async def main():
        stream = channel.stream()
        channel.publish({"n": 0})
        first = await stream.__anext__()
        for i in range(1, 20):  # arrive faster than the reader reads
            channel.publish({"n": i})
        await asyncio.sleep(0.01)
        rest = [item async for item in stream]
        return first, rest

    first, rest = asyncio.run(main())
    assert first == (1, {"n": 0}) and rest == []  # dropped: the stream ended
    assert channel.n_subscribers == 0
    channel.close()
    caught_up = asyncio.run(collect(channel, after=first[0]))
    assert [doc["n"] for _, doc in caught_up] == list(range(1, 20))


def test_heartbeats_while_nothing_happens():
    channel = EventChannel()

    async def main():
        items = []
        async for item in channel.stream(heartbeat_s=0.01):
            items.append(item)
            if len(items) == 2:
                channel.publish({"n": 1})
            if item is not None:
                return items

    assert asyncio.run(main()) == [None, None, (1, {"n": 1})]


def test_sse_message_format():
    assert sse_message(7, {"kind": "state", "state": "done"}) == \
        b'id: 7\ndata: {"kind":"state","state":"done"}\n\n'


def read_events(url: str, headers=None) -> list[tuple[int, dict]]:
    """Every (id, document) of an SSE stream until the server ends it."""
    events, event_id = [], None
    with httpx.Client(timeout=60) as client, client.stream("GET", url, headers=headers) as reply:
        assert reply.status_code == 200
        assert reply.headers["content-type"].startswith("text/event-stream")
        for line in reply.iter_lines():
            if line.startswith("id: "):
                event_id = int(line[4:])
            elif line.startswith("data: "):
                events.append((event_id, json.loads(line[6:])))
    return events


def test_many_clients_watch_one_scan_live_and_see_the_same_stream(tmp_path):
    with LiveServer(create_app(tmp_path / "state")) as server:
        body = {"plan": capture_plan(6, settle_s=0.05), **station_urls()}
        scan = httpx.post(f"{server.url}/api/v1/scans", json=body, timeout=30).json()
        url = f"{server.url}/api/v1/scans/{scan['id']}/events"
        results: list = [None] * 8

        def watch(i):
            results[i] = read_events(url)

        watchers = [threading.Thread(target=watch, args=(i,)) for i in range(8)]
        for watcher in watchers:
            watcher.start()
        for watcher in watchers:
            watcher.join(60)
        assert all(result == results[0] for result in results)
        kinds = [doc["kind"] for _, doc in results[0]]
        assert kinds[:3] == ["state", "state", "start"] and kinds[-2:] == ["stop", "state"]
        assert [doc["state"] for _, doc in results[0][:2]] == ["starting", "running"]
        assert kinds.count("view") == 6 and kinds.count("progress") == 6
        assert results[0][-1][1]["state"] == "done"
        ids = [event_id for event_id, _ in results[0]]
        assert ids == list(range(1, len(ids) + 1))
        # a client reconnecting with Last-Event-ID gets only what came after
        again = read_events(url, headers={"Last-Event-ID": str(ids[-3])})
        assert again == results[0][-2:]


def test_events_of_a_scan_from_an_earlier_daemon_give_its_state(tmp_path):
    state_dir = tmp_path / "state"
    with TestClient(create_app(state_dir)) as client:
        scan = client.post("/api/v1/scans", json={"plan": capture_plan(2), **station_urls()})
        wait_for_state(client, scan.json()["id"], "done")
    with TestClient(create_app(state_dir)) as client:
        text = client.get(f"/api/v1/scans/{scan.json()['id']}/events").text
        data = [json.loads(line[6:]) for line in text.splitlines() if line.startswith("data: ")]
        assert [(d["kind"], d["state"]) for d in data] == [("state", "done")]
