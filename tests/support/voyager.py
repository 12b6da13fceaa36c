"""Smithsonian Voyager Explorer (the built copy in ``../shared/tools/voyager-explorer``) opening a
published scene in headless Chromium, as its README says: the explorer served at ``/``, the scene
folder at ``/scene/``, from one origin on 127.0.0.1; loaded means the element fired ``model-load``;
failures are console errors, failed or refused requests and Voyager's red notices."""

from __future__ import annotations

import functools
import http.server
import json
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from jsonschema import Draft7Validator
from referencing import Registry, Resource

from shared.core.datapaths import shared_data_dir
from tests.support.viewer_browser import chromium

__all__ = ["SVX_SCHEMAS", "VOYAGER_DIR", "VoyagerResult", "open_in_voyager", "serve_static", "svx_validator"]

VOYAGER_DIR = shared_data_dir().parent / "tools" / "voyager-explorer"
SVX_SCHEMAS = shared_data_dir().parent / "reference" / "voyager-svx-schema"


def svx_validator() -> Draft7Validator:
    """A draft-07 validator of ``document.schema.json`` with the other four of Voyager's schemas registered."""
    docs = [json.loads(p.read_text()) for p in sorted(SVX_SCHEMAS.glob("*.schema.json"))]
    assert len(docs) == 5
    registry = Registry().with_resources([(d["$id"], Resource.from_contents(d)) for d in docs])
    root = next(d for d in docs if d["$id"].endswith("/document.schema.json"))
    Draft7Validator.check_schema(root)
    return Draft7Validator(root, registry=registry)
_TYPES = {".js": "application/javascript", ".glb": "model/gltf-binary", ".json": "application/json",
          ".wasm": "application/wasm", ".html": "text/html", ".css": "text/css", ".png": "image/png",
          ".ply": "application/octet-stream", ".woff": "font/woff", ".woff2": "font/woff2"}


class _Handler(http.server.SimpleHTTPRequestHandler):
    """Files under ``/scene/`` from the scene folder, everything else from Voyager's folder."""

    extensions_map = _TYPES

    def __init__(self, *args, voyager: Path, scene: Path, **kw) -> None:
        self._voyager, self._scene = voyager, scene
        super().__init__(*args, directory=str(voyager), **kw)

    def translate_path(self, path: str) -> str:
        clean = path.split("?", 1)[0].split("#", 1)[0]
        if clean.startswith("/scene/"):
            target = (self._scene / clean[len("/scene/"):]).resolve()
            return str(target) if target.is_relative_to(self._scene.resolve()) else str(self._scene / "__missing__")
        return super().translate_path(path)

    def log_message(self, *args: object) -> None:  # quiet
        pass


@contextmanager
def serve_static(scene: Path, voyager: Path = VOYAGER_DIR) -> Iterator[str]:
    """Serve Voyager and a scene folder on a free port; yields the base URL."""
    handler = functools.partial(_Handler, voyager=voyager, scene=scene)
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()


@dataclass
class VoyagerResult:
    loaded: int = 0
    console_errors: list[str] = field(default_factory=list)
    failed_requests: list[str] = field(default_factory=list)
    notices: list[str] = field(default_factory=list)
    model_requests: list[str] = field(default_factory=list)


_WATCH = """
window.__models = 0; window.__notices = [];
document.addEventListener('model-load', () => { window.__models += 1; }, true);
const seen = new Set();
const scan = (root) => {
  for (const el of root.querySelectorAll('*')) {
    if (el.shadowRoot) scan(el.shadowRoot);
    const t = (el.childElementCount === 0 && el.textContent) || '';
    if (/Failed to load/i.test(t) && !seen.has(t)) { seen.add(t); window.__notices.push(t.trim()); }
  }
};
setInterval(() => scan(document), 100);
"""


def open_in_voyager(scene: Path, screenshot: Path | None = None, timeout_s: float = 90.0,
                    settle_s: float = 3.0) -> VoyagerResult:
    """Open ``scene/scene.svx.json`` in Voyager Explorer; wait for the model (or ``timeout_s``), let it
    render ``settle_s`` more, take a screenshot."""
    res = VoyagerResult()
    with serve_static(scene) as base, chromium() as browser:
        page = browser.new_page(viewport={"width": 1024, "height": 720})
        page.on("console", lambda m: res.console_errors.append(m.text) if m.type == "error" else None)
        page.on("pageerror", lambda e: res.console_errors.append(str(e)))
        page.on("requestfailed", lambda r: res.failed_requests.append(f"{r.url} {r.failure}"))
        page.on("response", lambda r: res.failed_requests.append(f"{r.url} {r.status}") if r.status >= 400 else None)
        page.on("request", lambda r: res.model_requests.append(r.url) if r.url.endswith(".glb") else None)
        page.add_init_script(_WATCH)
        page.goto(f"{base}/offline.html")
        end = time.monotonic() + timeout_s
        while time.monotonic() < end and not page.evaluate("window.__models") and not res.console_errors:
            page.wait_for_timeout(250)
        page.wait_for_timeout(int(settle_s * 1000))
        res.loaded = int(page.evaluate("window.__models"))
        res.notices = list(page.evaluate("window.__notices"))
        if screenshot is not None:
            page.screenshot(path=str(screenshot))
        page.close()
    return res
