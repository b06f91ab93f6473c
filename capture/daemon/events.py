"""Fan-out of a scan's documents to many live clients (Server-Sent Events).

The runner publishes from its own thread; each client is an asyncio task on the server's event
loop with its own bounded queue, fed through ``loop.call_soon_threadsafe``. Documents are
numbered per scan (the SSE ``id``) and kept, so a client that connects late, or reconnects with
``Last-Event-ID``, first gets what it missed. A client too slow to keep up with its queue is
dropped (its stream ends; the browser reconnects and catches up from the history).
"""

from __future__ import annotations

import asyncio
import collections
import json
import threading
from collections.abc import AsyncIterator
from typing import Any

_END = object()
_OVERFLOW = object()


class _Subscriber:
    """One client's queue on one event loop; `offer` may be called from any thread."""

    def __init__(self, loop: asyncio.AbstractEventLoop, size: int):
        self.loop = loop
        self.queue: asyncio.Queue = asyncio.Queue(maxsize=size)
        self.dropped = False

    def offer(self, item) -> None:
        try:
            self.loop.call_soon_threadsafe(self._put, item)
        except RuntimeError:  # the loop is closed: the client is gone
            self.dropped = True

    def _put(self, item) -> None:
        if self.dropped:
            return
        try:
            self.queue.put_nowait(item)
        except asyncio.QueueFull:
            self.dropped = True
            while not self.queue.empty():
                self.queue.get_nowait()
            self.queue.put_nowait(_OVERFLOW)


class EventChannel:
    """The documents of one scan: numbered from 1, the last ``max_history`` kept, fanned out to
    every subscriber. `publish` and `close` are thread-safe; `stream` runs on an event loop."""

    def __init__(self, max_history: int = 10_000, queue_size: int = 1_000):
        self._lock = threading.Lock()
        self._history: collections.deque[tuple[int, dict]] = collections.deque(maxlen=max_history)
        self._next_id = 1
        self._subscribers: set[_Subscriber] = set()
        self._queue_size = queue_size
        self.closed = False

    @property
    def last_id(self) -> int:
        return self._next_id - 1

    @property
    def n_subscribers(self) -> int:
        return len(self._subscribers)

    def publish(self, doc: dict[str, Any]) -> int:
        """Number, keep and send ``doc`` to every live subscriber; returns its id."""
        with self._lock:
            event = (self._next_id, doc)
            self._next_id += 1
            self._history.append(event)
            subscribers = list(self._subscribers)
        for subscriber in subscribers:
            subscriber.offer(event)
        return event[0]

    def close(self) -> None:
        """No more documents for now: live streams end after what they have."""
        with self._lock:
            self.closed = True
            subscribers = list(self._subscribers)
        for subscriber in subscribers:
            subscriber.offer(_END)

    def reopen(self) -> None:
        """The scan runs again (resume, re-process): new streams stay open."""
        with self._lock:
            self.closed = False

    async def stream(
        self, after: int = 0, heartbeat_s: float | None = None
    ) -> AsyncIterator[tuple[int, dict] | None]:
        """(id, doc) for every document after id ``after``, live until the channel closes.
        Yields None after ``heartbeat_s`` seconds without a document (keep-alive)."""
        subscriber = _Subscriber(asyncio.get_running_loop(), self._queue_size)
        with self._lock:
            backlog = [event for event in self._history if event[0] > after]
            closed = self.closed
            if not closed:
                self._subscribers.add(subscriber)
        try:
            for event in backlog:
                yield event
            while not closed:
                try:
                    item = await asyncio.wait_for(subscriber.queue.get(), heartbeat_s)
                except asyncio.TimeoutError:
                    yield None
                    continue
                if item is _END or item is _OVERFLOW:
                    return
                yield item
        finally:
            with self._lock:
                self._subscribers.discard(subscriber)


class EventHub:
    """One `EventChannel` per scan id."""

    def __init__(self, **channel_options):
        self._lock = threading.Lock()
        self._channels: dict[str, EventChannel] = {}
        self._options = channel_options

    def channel(self, scan_id: str) -> EventChannel:
        with self._lock:
            if scan_id not in self._channels:
                self._channels[scan_id] = EventChannel(**self._options)
            return self._channels[scan_id]

    def drop(self, scan_id: str) -> None:
        with self._lock:
            channel = self._channels.pop(scan_id, None)
        if channel is not None:
            channel.close()

    def close_all(self) -> None:
        with self._lock:
            channels = list(self._channels.values())
        for channel in channels:
            channel.close()


def sse_message(event_id: int, doc: dict[str, Any]) -> bytes:
    """One Server-Sent Events message: the document as JSON in ``data``, its number in ``id``."""
    return f"id: {event_id}\ndata: {json.dumps(doc, separators=(',', ':'))}\n\n".encode()


SSE_KEEPALIVE = b": keep-alive\n\n"
