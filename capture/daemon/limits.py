"""Request body limits (plain ASGI middleware): 413 before the application sees the body,
408 when the body stops coming.

A declared ``Content-Length`` over the limit is refused at once; a body sent in chunks is
counted as it arrives and refused as soon as it passes the limit, so no request can make the
daemon buffer more than ``max_bytes``. Each part of the body must arrive within ``timeout_s``:
a client that stops short of its Content-Length holds no connection for long.
"""

from __future__ import annotations

import asyncio
import json

_WITH_BODY = frozenset({"POST", "PUT", "PATCH", "DELETE"})


class BodySizeLimit:
    """Wrap an ASGI app: bodies of at most ``max_bytes`` bytes, else 413 with a JSON message;
    at most ``timeout_s`` seconds between two parts of a body, else 408."""

    def __init__(self, app, max_bytes: int, timeout_s: float = 10.0):
        if max_bytes < 0 or not timeout_s > 0:
            raise ValueError(f"max_bytes must be >= 0 and timeout_s > 0, got {max_bytes}, "
                             f"{timeout_s}")
        self.app = app
        self.max_bytes = max_bytes
        self.timeout_s = timeout_s

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http" or scope["method"] not in _WITH_BODY:
            await self.app(scope, receive, send)
            return
        declared = dict(scope["headers"]).get(b"content-length")
        if declared is not None:
            try:
                too_big = int(declared) > self.max_bytes
            except ValueError:
                await self._reply(send, 400, "Content-Length is not a number")
                return
            if too_big:
                await self._reject(send)
                return
        chunks, size = [], 0
        while True:
            try:
                message = await asyncio.wait_for(receive(), self.timeout_s)
            except asyncio.TimeoutError:
                await self._reply(send, 408, f"request body not received within "
                                  f"{self.timeout_s:g} s")
                return
            if message["type"] == "http.disconnect":
                return
            body = message.get("body", b"")
            size += len(body)
            if size > self.max_bytes:
                await self._reject(send)
                return
            chunks.append(body)
            if not message.get("more_body", False):
                break
        buffered = {"type": "http.request", "body": b"".join(chunks), "more_body": False}

        async def replay():
            nonlocal buffered
            if buffered is not None:
                message, buffered = buffered, None
                return message
            return await receive()

        await self.app(scope, replay, send)

    async def _reject(self, send) -> None:
        await self._reply(send, 413, f"request body larger than {self.max_bytes} bytes")

    @staticmethod
    async def _reply(send, status: int, detail: str) -> None:
        body = json.dumps({"detail": detail}).encode()
        await send({"type": "http.response.start", "status": status, "headers": [
            (b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
            (b"connection", b"close")]})
        await send({"type": "http.response.body", "body": body})
