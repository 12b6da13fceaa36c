"""Every derivative GLB loads in three.js's GLTFLoader with the official Draco decoder, in a real
headless Chromium (WebGL2 on SwiftShader), draws textured, and is looked at as a PNG."""

from __future__ import annotations

import base64
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from fastapi import FastAPI
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles

from shared.derive.pipeline import make_derivatives
from tests.support.derive_scene import write_scene
from tests.support.viewer_browser import VIEWER_DIR, Server, chromium

pytestmark = pytest.mark.slow

THREE = VIEWER_DIR / "node_modules" / "three"

PAGE = """<!doctype html><html><body style="margin:0"><canvas id="c" width="480" height="360"></canvas>
<script type="importmap">{"imports": {"three": "/three/build/three.module.js",
 "three/addons/": "/three/examples/jsm/"}}</script>
<script type="module">
import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";
import { DRACOLoader } from "three/addons/loaders/DRACOLoader.js";
const canvas = document.getElementById("c");
const renderer = new THREE.WebGLRenderer({ canvas, preserveDrawingBuffer: true });
renderer.outputColorSpace = THREE.SRGBColorSpace;
const draco = new DRACOLoader().setDecoderPath("/three/examples/jsm/libs/draco/");
const loader = new GLTFLoader().setDRACOLoader(draco);
window.load = async (name) => {
  const gltf = await loader.loadAsync("/glb/" + name);
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(0.1, 0.1, 0.12);
  scene.add(new THREE.HemisphereLight(0xffffff, 0x444444, 2.0));
  const sun = new THREE.DirectionalLight(0xffffff, 1.5); sun.position.set(1, 1, 2); scene.add(sun);
  scene.add(gltf.scene);
  let triangles = 0, mat = null;
  gltf.scene.traverse((o) => { if (o.isMesh) { triangles += o.geometry.index.count / 3; mat = o.material; } });
  const box = new THREE.Box3().setFromObject(gltf.scene);
  const c = box.getCenter(new THREE.Vector3()), r = box.getSize(new THREE.Vector3()).length() / 2;
  const cam = new THREE.PerspectiveCamera(40, canvas.width / canvas.height, r / 100, r * 100);
  cam.position.set(c.x + r * 1.2, c.y + r * 0.6, c.z + r * 2.2); cam.lookAt(c);
  sun.position.copy(cam.position);
  renderer.render(scene, cam);
  return { triangles, extras: gltf.parser.json.asset.extras,
           map: mat.map ? [mat.map.image.width, mat.map.image.height] : null,
           normalMap: !!mat.normalMap, aoMap: !!mat.aoMap, png: canvas.toDataURL("image/png") };
};
window.ready = true;
</script></body></html>"""


def _app(glb_dir: Path) -> FastAPI:
    app = FastAPI()
    app.mount("/three", StaticFiles(directory=THREE), name="three")
    app.mount("/glb", StaticFiles(directory=glb_dir), name="glb")
    app.add_api_route("/", lambda: HTMLResponse(PAGE), methods=["GET"])
    return app


def test_every_derivative_loads_in_gltfloader_with_draco_and_draws_textured(tmp_path: Path) -> None:
    if not (THREE / "examples" / "jsm" / "libs" / "draco" / "draco_decoder.wasm").is_file():
        pytest.fail("three is missing from services/viewer/node_modules: run `make viewer`")
    scene = write_scene(tmp_path / "merge", faces_subdiv=5, points=200_000)
    out = tmp_path / "derived"
    report = make_derivatives(scene, out, levels="thumb:4000:256,low:20000:512")
    errors: list[str] = []
    with Server(_app(out)) as server, chromium() as browser:
        page = browser.new_page(viewport={"width": 480, "height": 360})
        # Failed requests by URL (the console's "Failed to load resource" names none); the page has no favicon.
        page.on("response", lambda r: errors.append(f"{r.status} {r.url}")
                if r.status >= 400 and not r.url.endswith("/favicon.ico") else None)
        page.on("console", lambda m: errors.append(m.text)
                if m.type == "error" and not m.text.startswith("Failed to load resource") else None)
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(server.url + "/")
        page.wait_for_function("() => window.ready === true", timeout=30_000)
        for lv in report["levels"]:
            got = page.evaluate("(n) => window.load(n)", lv["file"])
            assert not errors, errors
            assert got["triangles"] == lv["faces"]
            assert got["map"] == [lv["texture_px"], lv["texture_px"]] and got["normalMap"] and got["aoMap"]
            assert got["extras"]["units"] == "mm" and got["extras"]["level"] == lv["level"]
            png = base64.b64decode(got["png"].split(",", 1)[1])
            (tmp_path / f"{lv['level']}.png").write_bytes(png)
            img = cv2.cvtColor(cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
            # The object fills the middle of the frame, in its pattern's colours (not one flat shade).
            centre = img[120:240, 160:320].reshape(-1, 3).astype(float)
            background = np.array([0.1, 0.1, 0.12]) * 255
            assert np.mean(np.abs(centre - background).sum(axis=1) > 60) > 0.9
            hue = cv2.cvtColor(img[120:240, 160:320], cv2.COLOR_RGB2HSV)[..., 0]
            assert np.ptp(np.percentile(hue, [10, 90])) > 20, json.dumps(lv)
