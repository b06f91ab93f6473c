"""Bearer token: made once with mode 0600, required off loopback, 401 without it."""

from __future__ import annotations

import stat

import pytest
from fastapi.testclient import TestClient

from capture.daemon.app import create_app
from capture.daemon.auth import BearerAuth, host_of, is_loopback, load_or_create_token


def test_the_token_is_made_once_with_mode_0600(tmp_path):
    token, created = load_or_create_token(tmp_path)
    path = tmp_path / "token"
    assert created and len(token) >= 40
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    again, created_again = load_or_create_token(tmp_path)
    assert (again, created_again) == (token, False)


def test_a_token_file_readable_by_others_is_tightened(tmp_path, caplog):
    token, _ = load_or_create_token(tmp_path)
    path = tmp_path / "token"
    path.chmod(0o644)
    assert load_or_create_token(tmp_path) == (token, False)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert "readable by others" in caplog.text
    path.write_text("\n")
    with pytest.raises(ValueError, match="is empty"):
        load_or_create_token(tmp_path)


@pytest.mark.parametrize("host, loopback", [
    ("127.0.0.1", True), ("127.1.2.3", True), ("::1", True), ("[::1]", True),
    ("localhost", True), ("0.0.0.0", False), ("::", False), ("192.168.1.20", False),
    ("scanner.local", False),
])
def test_loopback_addresses(host, loopback):
    assert is_loopback(host) is loopback


def test_bearer_check():
    auth = BearerAuth("s3cret", required=True)
    assert auth.check("Bearer s3cret") and auth.check("bearer s3cret")
    for header in (None, "", "Bearer", "Bearer wrong", "Basic s3cret", "s3cret"):
        assert not auth.check(header)
    assert BearerAuth("", required=False).check(None)
    with pytest.raises(ValueError):
        BearerAuth("", required=True)


def test_with_a_required_token_the_api_answers_401_without_it(tmp_path):
    token, _ = load_or_create_token(tmp_path)
    app = create_app(tmp_path / "state", token=token, require_token=True)
    with TestClient(app) as client:
        for path in ("/api/v1/scans", "/api/v1/devices", "/api/v1/scans/0123456789abcdef/events"):
            answer = client.get(path)
            assert answer.status_code == 401, path
            assert answer.headers["www-authenticate"] == "Bearer"
            assert "bearer token" in answer.json()["detail"]
        assert client.post("/api/v1/scans", json={}).status_code == 401
        wrong = {"Authorization": "Bearer nope"}
        assert client.get("/api/v1/scans", headers=wrong).status_code == 401
        right = {"Authorization": f"Bearer {token}"}
        assert client.get("/api/v1/scans", headers=right).json() == {"scans": []}
        # the page, its assets, the docs and the health check carry no secrets
        for path in ("/", "/static/app.js", "/docs", "/openapi.json", "/healthz"):
            assert client.get(path).status_code == 200, path
        assert client.get("/healthz").json()["token_required"] is True


def test_on_loopback_no_token_is_needed(tmp_path):
    with TestClient(create_app(tmp_path / "state", token="t", require_token=False)) as client:
        assert client.get("/api/v1/scans").status_code == 200


@pytest.mark.parametrize("header, host", [
    ("127.0.0.1:8765", "127.0.0.1"), ("localhost", "localhost"), ("[::1]:8765", "::1"),
    ("[::1]", "::1"), ("evil.example:80", "evil.example"), ("::1", "::1"),
])
def test_host_of_a_host_header(header, host):
    assert host_of(header) == host


def test_a_token_free_daemon_answers_only_to_loopback_host_names(tmp_path):
    """DNS rebinding: a foreign page whose name resolves to 127.0.0.1 still sends its name."""
    app = create_app(tmp_path / "state", loopback_hosts_only=True)
    with TestClient(app, base_url="http://127.0.0.1:8765") as client:
        assert client.get("/api/v1/scans").status_code == 200
        for host in ("localhost:8765", "[::1]:8765", "127.0.0.1"):
            assert client.get("/healthz", headers={"host": host}).status_code == 200, host
        for host in ("evil.example:8765", "scanner.local", ""):
            answer = client.post("/api/v1/scans/0123456789abcdef/cancel", headers={"host": host})
            assert answer.status_code == 421, host
            assert "loopback Host" in answer.json()["detail"]


def test_a_token_file_that_is_a_link_is_refused(tmp_path):
    elsewhere = tmp_path / "elsewhere"
    elsewhere.write_text("someone-elses-secret\n")
    (tmp_path / "state").mkdir()
    (tmp_path / "state" / "token").symlink_to(elsewhere)
    with pytest.raises(ValueError, match="not a regular file"):
        load_or_create_token(tmp_path / "state")
