"""The web page end to end in a real headless Chromium (Debian's, driven by playwright): start a
scan from the form, follow it live, see the mesh in 3D, move the λ slider, take a screenshot."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from daemon_helpers import MESH_CAMERA, LiveServer, station_urls

from capture.daemon.app import create_app

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
BACKGROUND = (0x20, 0x24, 0x2C)  # the viewer's clear colour


# CI sets SCANSTATION_REQUIRE_BROWSER=1: there a missing browser fails instead of skipping.
REQUIRED = os.environ.get("SCANSTATION_REQUIRE_BROWSER") == "1"
# Where the screenshot is kept (CI: .ci/artifacts); else the test's own tmp folder.
ARTIFACTS = os.environ.get("SCANSTATION_ARTIFACTS")


def _unavailable(reason: str):
    (pytest.fail if REQUIRED else pytest.skip)(reason)


@pytest.fixture
def page(tmp_path):
    if CHROMIUM is None:
        _unavailable("no chromium on this machine (Debian: apt-get install chromium)")
    try:
        from playwright import sync_api
    except ImportError:
        _unavailable("playwright is not installed (pip install playwright)")
    with sync_api.sync_playwright() as playwright:
        browser = playwright.chromium.launch(
            executable_path=CHROMIUM, headless=True,
            args=["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"])
        context = browser.new_context(viewport={"width": 1280, "height": 900})
        page = context.new_page()
        errors: list[str] = []
        page.on("pageerror", lambda error: errors.append(str(error)))
        page.on("console", lambda m: m.type == "error" and errors.append(m.text))
        page.errors = errors
        requested: list[str] = []
        page.on("request", lambda request: requested.append(request.url))
        page.requested = requested
        yield page
        context.close()
        browser.close()


def viewer_pixels(png: bytes, box: dict) -> np.ndarray:
    """(h, w, 3) uint8 of the screenshot inside ``box`` (CSS pixels, device scale 1)."""
    from io import BytesIO

    from PIL import Image

    image = np.asarray(Image.open(BytesIO(png)).convert("RGB"))
    x, y, w, h = (int(round(box[k])) for k in ("x", "y", "width", "height"))
    return image[y:y + h, x:x + w]


def test_start_watch_view_and_refine_in_a_real_browser(page, tmp_path):
    with LiveServer(create_app(tmp_path / "state")) as server:
        page.goto(server.url + "/")
        page.wait_for_selector("body[data-ready='1']")
        assert page.inner_text("#health") == "daemon up"
        urls = station_urls(**MESH_CAMERA)
        page.fill("input[name=views]", "6")
        page.fill("input[name=frames]", "1")
        page.select_option("select[name=reconstruction]", "preview")
        page.fill("input[name=camera_url]", urls["camera_url"])
        page.fill("input[name=turntable_url]", urls["turntable_url"])
        page.click("#start")

        # live progress over SSE, then the mesh in the viewer
        page.wait_for_function("document.getElementById('log').children.length > 3",
                               timeout=60_000)
        page.wait_for_selector("body[data-scan-state='done']", timeout=180_000)
        assert page.inner_text("#progress-text") == "6 / 6 views"
        page.wait_for_selector("body[data-mesh-version]", timeout=60_000)
        first = int(page.get_attribute("body", "data-mesh-version"))
        assert "faces" in page.inner_text("#viewer-note")
        log = page.text_content("#log")
        for kind in ("start", "view", "progress", "mesh", "stop"):
            assert f" {kind} " in log, kind

        # the λ slider re-meshes through the API and the viewer reloads the mesh
        page.eval_on_selector("#lam", "el => { el.value = '4'; "
                                      "el.dispatchEvent(new Event('input')); }")
        page.wait_for_function(f"Number(document.body.dataset.meshVersion) > {first}",
                               timeout=60_000)
        page.wait_for_function("document.getElementById('refine-status').textContent"
                               ".includes('λ 4')", timeout=60_000)

        shot = Path(ARTIFACTS or tmp_path) / "daemon-page.png"
        shot.parent.mkdir(parents=True, exist_ok=True)
        png = page.screenshot(path=str(shot), full_page=True)
        assert shot.stat().st_size > 10_000
        viewer = viewer_pixels(png, page.locator("#canvas").bounding_box())
        assert viewer.shape[0] > 300 and viewer.shape[1] > 300
        distance = np.abs(viewer.astype(int) - BACKGROUND).sum(axis=2)
        drawn = (distance > 40).mean()
        assert 0.02 < drawn < 0.9, f"the mesh covers {drawn:.1%} of the viewer"
        whole = np.asarray(viewer_pixels(png, {"x": 0, "y": 0, "width": 1280, "height": 900}))
        assert len(np.unique(whole.reshape(-1, 3), axis=0)) > 50  # not a blank page
        assert page.errors == []

        # the API docs render from the daemon's own assets too
        page.goto(server.url + "/docs")
        page.wait_for_selector(".swagger-ui .opblock", timeout=30_000)
        assert "/api/v1/scans/{scan_id}/refine" in page.inner_text(".swagger-ui")
        outside = [url for url in page.requested
                   if not url.startswith((server.url, "data:", "blob:"))]
        assert outside == []  # no CDN: offline stations work


def test_the_page_asks_for_the_token_when_one_is_required(page, tmp_path):
    app = create_app(tmp_path / "state", token="let-me-in", require_token=True)
    with LiveServer(app) as server:
        page.goto(server.url + "/")
        page.wait_for_selector("#token-form:not([hidden])")  # the first API call got 401
        page.fill("#token", "let-me-in")
        page.click("#token-form button")
        page.wait_for_selector("#token-form", state="hidden")
        page.fill("input[name=views]", "2")
        page.fill("input[name=frames]", "1")
        page.select_option("select[name=reconstruction]", "none")
        for name, url in station_urls().items():
            page.fill(f"input[name={name}]", url)
        page.click("#start")
        page.wait_for_selector("body[data-scan-state='done']", timeout=60_000)
        assert page.inner_text("#progress-text") == "2 / 2 views"
        page.wait_for_function("document.querySelectorAll('#scans li').length === 1")
