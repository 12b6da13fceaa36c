"""The web viewer in a real headless Chromium: build the assets, serve an app, drive a page.

Debian's Chromium (``/usr/bin/chromium``, WebGL2 on SwiftShader) through Playwright; no browser
downloads. The app is served by uvicorn on 127.0.0.1 (a free port) in a thread.
"""

from __future__ import annotations

import base64
import shutil
import socket
import subprocess
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np
import pytest
from fastapi import FastAPI

from services.viewer import routes
from tests.support.locks import held

__all__ = ["CHROMIUM", "CHROMIUM_ARGS", "VIEWER_DIR", "Page", "Server", "built_viewer", "chromium", "rays_through_pixels"]

VIEWER_DIR = Path(routes.__file__).resolve().parent
CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--use-gl=angle",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]


def _sources_newer_than_build() -> bool:
    built = VIEWER_DIR / "dist" / "assets" / "viewer.js"
    if not built.is_file() or not (VIEWER_DIR / "dist" / "index.html").is_file():
        return True
    stamp = built.stat().st_mtime
    sources = [*VIEWER_DIR.glob("src/*"), VIEWER_DIR / "build.mjs", VIEWER_DIR / "package-lock.json"]
    return any(p.stat().st_mtime > stamp for p in sources)


def built_viewer() -> Path:
    """The viewer's ``dist`` folder, rebuilt with npm when the sources changed since the last build."""
    # Test processes may run this at once: one builds while the others wait on the lock.
    with held(Path(tempfile.gettempdir()) / "graylight-viewer-build.lock"):
        if _sources_newer_than_build():
            npm = shutil.which("npm")
            if npm is None or not (VIEWER_DIR / "node_modules").is_dir():
                pytest.fail("viewer assets missing or stale and npm/node_modules unavailable: run `make viewer`")
            subprocess.run([npm, "run", "--silent", "build"], cwd=VIEWER_DIR, check=True, timeout=120)
    return VIEWER_DIR / "dist"


class Server:
    """uvicorn serving ``app`` on 127.0.0.1 (a free port) in a thread."""

    def __init__(self, app: FastAPI) -> None:
        import uvicorn

        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.sock.bind(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.server = uvicorn.Server(uvicorn.Config(app, log_level="warning", lifespan="off"))
        self.thread = threading.Thread(target=self.server.run, kwargs={"sockets": [self.sock]}, daemon=True)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def __enter__(self) -> Server:
        self.thread.start()
        deadline = time.monotonic() + 10
        while not self.server.started:
            if time.monotonic() > deadline:
                raise RuntimeError("uvicorn did not start")
            time.sleep(0.02)
        return self

    def __exit__(self, *exc: object) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=5)
        self.sock.close()


@contextmanager
def chromium() -> Iterator[object]:
    """A headless Chromium browser (Playwright ``Browser``); fails the test when it is missing."""
    from playwright.sync_api import sync_playwright

    if not CHROMIUM.exists():
        pytest.fail(f"{CHROMIUM} is missing: `apt-get install chromium` (make setup installs it)")
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        try:
            yield browser
        finally:
            browser.close()


class Page:
    """A viewer page with console errors and page errors collected."""

    def __init__(self, browser, url: str, size: tuple[int, int] = (640, 480)) -> None:
        self.page = browser.new_page(viewport={"width": size[0], "height": size[1]}, device_scale_factor=1)
        self.errors: list[str] = []
        self.page.on("console", lambda m: self.errors.append(m.text) if m.type == "error" else None)
        self.page.on("pageerror", lambda e: self.errors.append(str(e)))
        self.page.goto(url)

    def wait_idle(self, timeout_s: float = 60.0) -> dict:
        self.page.wait_for_function("() => window.graylight && window.graylight.idle()", timeout=timeout_s * 1000, polling=100)
        return self.page.evaluate("() => window.graylight.state()")

    def capture(self) -> np.ndarray:
        """The frame as RGB uint8 (H, W, 3), read back from the WebGL canvas."""
        data_url = self.page.evaluate("() => window.graylight.capture()")
        png = base64.b64decode(data_url.split(",", 1)[1])
        bgr = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)

    def set(self, **settings: object) -> dict:
        self.page.evaluate("(s) => window.graylight.set(s)", settings)
        return self.wait_idle()

    def look_at(self, eye: np.ndarray, target: np.ndarray) -> dict:
        self.page.evaluate("([e, t]) => window.graylight.lookAt(e, t)", [list(map(float, eye)), list(map(float, target))])
        return self.wait_idle()

    def close(self) -> None:
        self.page.close()


def rays_through_pixels(eye: np.ndarray, target: np.ndarray, fov_deg: float, size: tuple[int, int]) -> np.ndarray:
    """Unit world rays (H, W, 3) through the pixel centres of the viewer's camera (up = -y, lookAt)."""
    width, height = size
    up = np.array([0.0, -1.0, 0.0])
    z_axis = (eye - target) / np.linalg.norm(eye - target)
    x_axis = np.cross(up, z_axis)
    x_axis /= np.linalg.norm(x_axis)
    y_axis = np.cross(z_axis, x_axis)
    f = height / 2 / np.tan(np.radians(fov_deg) / 2)
    u, v = np.meshgrid(np.arange(width) + 0.5 - width / 2, height / 2 - (np.arange(height) + 0.5))
    d = u[..., None] * x_axis + v[..., None] * y_axis - f * z_axis
    return d / np.linalg.norm(d, axis=-1, keepdims=True)
