"""Bearer-token access: a token made at first start, kept in the state dir with mode 0600, and
required on every API request when the daemon listens on anything but loopback."""

from __future__ import annotations

import hmac
import ipaddress
import logging
import os
import re
import secrets
import stat
from pathlib import Path

from fastapi import HTTPException, Request

log = logging.getLogger(__name__)

TOKEN_FILE = "token"


def is_loopback(host: str) -> bool:
    """True for 127.0.0.0/8, ::1 and ``localhost``; anything else (0.0.0.0, names) is not."""
    host = host.strip().strip("[]")
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def load_or_create_token(state_dir: str | Path) -> tuple[str, bool]:
    """(token, created): read ``state_dir/token``, or write a new random one with mode 0600.

    A token file readable by others is tightened to 0600 (with a warning) rather than trusted
    as is; an empty one is an error.
    """
    path = Path(state_dir) / TOKEN_FILE
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        if path.is_symlink() or not path.is_file():
            raise ValueError(f"{path} is not a regular file (a link?): delete it to make a new "
                             "token") from None
        mode = stat.S_IMODE(path.stat().st_mode)
        if mode & 0o077:
            log.warning("%s was readable by others (mode %o); set to 0600", path, mode)
            path.chmod(0o600)
        token = path.read_text().strip()
        if not token:
            raise ValueError(f"{path} is empty: delete it to make a new token") from None
        return token, False
    token = secrets.token_urlsafe(32)
    with os.fdopen(fd, "w") as file:
        file.write(token + "\n")
    return token, True


class BearerAuth:
    """FastAPI dependency: 401 unless ``Authorization: Bearer <token>`` matches (when required)."""

    def __init__(self, token: str, required: bool):
        if required and not token:
            raise ValueError("a token is required but none was given")
        self.token = token
        self.required = required

    def check(self, header: str | None) -> bool:
        if not self.required:
            return True
        scheme, _, given = (header or "").partition(" ")
        if scheme.lower() != "bearer" or not given:
            return False
        return hmac.compare_digest(given.strip().encode(), self.token.encode())

    async def __call__(self, request: Request) -> None:
        if not self.check(request.headers.get("authorization")):
            raise HTTPException(
                status_code=401,
                detail="missing or wrong bearer token (see the token file in the state dir)",
                headers={"WWW-Authenticate": "Bearer"},
            )


_HOST_HEADER = re.compile(
    r"^(?:\[(?P<v6>[0-9A-Fa-f:.]+)\]|(?P<name>[A-Za-z0-9.\-]+))(?::(?P<port>\d{1,5}))?$")


def host_of(header: str) -> str:
    """The host part of a ``Host`` header: ``[::1]:8765`` → ``::1``, ``a:80`` → ``a``; ""
    for anything that is not a plain host and port (``127.0.0.1:80@evil.example``)."""
    header = header.strip()
    match = _HOST_HEADER.match(header)
    if match:
        return match.group("v6") or match.group("name")
    try:  # a bare IPv6 address (``::1``)
        return str(ipaddress.IPv6Address(header))
    except ValueError:
        return ""


class LoopbackHostGuard:
    """Wrap an ASGI app: 421 unless the request's ``Host`` names a loopback address.

    A token-free daemon on loopback trusts whoever can reach it; this keeps out a web page on
    another site that rebinds its own name to 127.0.0.1 (DNS rebinding), since its requests
    still carry that name as their Host."""

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] in ("http", "websocket"):
            host = dict(scope["headers"]).get(b"host", b"").decode("latin-1")
            if not is_loopback(host_of(host)):
                body = (b'{"detail":"this daemon answers only to a loopback Host '
                        b'(localhost, 127.0.0.1, [::1])"}')
                await send({"type": "http.response.start", "status": 421, "headers": [
                    (b"content-type", b"application/json"),
                    (b"content-length", str(len(body)).encode())]})
                await send({"type": "http.response.body", "body": body})
                return
        await self.app(scope, receive, send)
