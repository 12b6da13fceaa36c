"""Hostile tenants (issue 21, findings 1, 2, 8 and 9) against the real API, Redis and a worker.

Each test would pass a probe of the old code only by luck: there, a scan set's absolute or
``..`` cloud was merged into the job's result and a missing one said so in other words than an
existing one; ``params.preview.path`` named a file on the render worker (a FIFO blocked it, and
``/dev/zero`` filled its memory); a ``capture_ref`` symlinked out of the store was copied; and a
5000-digit number, a PLY header of 10^12 vertices, ``tiles.max_chunk`` of 1e30, a 1x1 capture,
a rig of 1e308 or over 1 MiB failed late, naming no file or with a bare exception name.

The reads of FIFOs and ``/dev/zero`` run in a child process under a memory limit and a time-out,
so a regression fails the test instead of hanging CI or the machine.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import zipfile
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from services.api.app import create_app
from shared.formats.ply import write_ply
from shared.service.jobstore import JobStore
from tests.support import jobsvc

# One group: the module's service (a worker process) starts on one xdist worker, not once a worker.
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("confinement")]

NO_RENDER = '{"render": false, "export": false}'
#: Internal words no failed stage's message may carry.
LEAKS = ("Error:", "MemoryError", "OverflowError", "RecursionError", "ValueError", "Traceback")


class Svc:
    """One job service for the module: API in-process, a real worker process, Redis, SQLite."""

    def __init__(self, senv: jobsvc.ServiceEnv, worker: jobsvc.Proc) -> None:
        self.senv = senv
        self.worker = worker
        _rec, key = JobStore(senv.settings.database_url).create_key("tenant")
        self.client = TestClient(create_app(senv.settings))
        self.auth = {"Authorization": f"Bearer {key}"}

    def submit(self, archive: Path, kind: str = "scan", params: str = NO_RENDER, **files) -> tuple[int, dict]:
        parts = {"capture": (archive.name, archive.read_bytes(), "application/zip"), **files}
        r = self.client.post("/v1/jobs", headers=self.auth, files=parts, data={"params": params, "kind": kind})
        return r.status_code, r.json()

    def run(self, archive: Path, kind: str = "scan", params: str | None = None, timeout: float = 120) -> dict:
        params = params or (NO_RENDER if kind == "scan" else '{"render": false}')
        code, doc = self.submit(archive, kind, params)
        assert code == 201, doc
        out: dict = {}

        def done() -> bool:
            out.update(self.client.get(f"/v1/jobs/{doc['id']}", headers=self.auth).json())
            return out["state"] in ("succeeded", "failed", "cancelled")

        jobsvc.wait_for(done, timeout, f"job {doc['id']} final", self.worker, interval=0.2)
        return out

    def artifacts(self, job: dict) -> set[str]:
        r = self.client.get(f"/v1/jobs/{job['id']}/artifacts", headers=self.auth)
        return {a["name"] for a in r.json()["artifacts"]}


@pytest.fixture(scope="module")
def svc(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Svc]:
    with jobsvc.service_env(tmp_path_factory.mktemp("confine")) as senv:
        yield Svc(senv, jobsvc.start_worker(senv))


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return jobsvc.simulate_small(tmp_path_factory.mktemp("cap") / "plane")


def _zip(out: Path, files: dict[str, bytes]) -> Path:
    with zipfile.ZipFile(out, "w") as z:
        for name, data in files.items():
            z.writestr(name, data)
    return out


def _scanset_zip(out: Path, doc: dict, extra: dict[str, bytes] | None = None) -> Path:
    return _zip(out, {"scanset.json": json.dumps(doc).encode(), **(extra or {})})


def _error(job: dict) -> str:
    assert job["state"] == "failed", job
    msg = job["error"]
    assert "\n" not in msg and not any(w in msg for w in LEAKS), msg
    return msg


def _outside_ply(folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    return write_ply(folder / "secret.ply", rng.normal(size=(500, 3)).astype(np.float32) * 10 + [0, 0, 500])


# ---- finding 1: scan-set paths --------------------------------------------------------------------


def test_scanset_paths_outside_the_archive_are_refused_alike(svc: Svc, tmp_path: Path, capture: Path) -> None:
    """Absolute and ``..`` clouds, an outside capture folder and rig are refused by the job's first
    stage naming the field; the text is the same for an existing PLY, a missing file and a file
    that is no PLY; nothing of the outside file reaches an artifact."""
    secret = _outside_ply(tmp_path / "outside")
    not_ply = tmp_path / "outside" / "notes.txt"
    not_ply.write_text("not a cloud\n")
    missing = tmp_path / "outside" / "gone.ply"
    depth = "../" * 30
    view = {"cloud": "ok.ply"}
    ok = {"ok.ply": (tmp_path / "outside" / "secret.ply").read_bytes()}
    cases = {
        "existing": ({"views": [{"cloud": str(secret)}, view]}, str(secret)),
        "missing": ({"views": [{"cloud": str(missing)}, view]}, str(missing)),
        "not a ply": ({"views": [{"cloud": str(not_ply)}, view]}, str(not_ply)),
        "dotdot existing": ({"views": [{"cloud": depth + str(secret).lstrip("/")}, view]}, depth + str(secret).lstrip("/")),
        "dotdot missing": ({"views": [{"cloud": depth + str(missing).lstrip("/")}, view]}, depth + str(missing).lstrip("/")),
    }
    texts = {}
    for i, (name, (doc, value)) in enumerate(cases.items()):
        job = svc.run(_scanset_zip(tmp_path / f"s{i}.zip", {"format": "graylight-scanset-v1", **doc}, ok), "multiview")
        msg = _error(job)
        assert "views[0].cloud: must be a relative path to a file inside the scan set folder" in msg, (name, msg)
        texts[name] = msg.replace(repr(value) if len(repr(value)) <= 80 else repr(value)[:77] + "...", "VALUE")
        assert not svc.artifacts(job), job  # nothing of the outside file reached an artifact
    assert len(set(texts.values())) == 1, texts  # exists, missing, not a PLY: one text
    # The rig and a captured view's folder alike.
    rig = svc.run(_scanset_zip(tmp_path / "r.zip", {"format": "graylight-scanset-v1", "rig": str(not_ply),
                                                     "views": [view, {"cloud": "ok.ply", "name": "b"}]}, ok), "multiview")
    assert "rig: must be a relative path to a file inside the scan set folder" in _error(rig)
    cap = svc.run(_scanset_zip(tmp_path / "c.zip", {"format": "graylight-scanset-v1",
                                                     "views": [{"capture": str(capture)}, view]}, ok), "multiview")
    assert "views[0].capture: must be a relative path to a folder inside the scan set folder" in _error(cap)


# ---- finding 2: the camera path of a preview --------------------------------------------------------


_READER = """
import resource, sys
resource.setrlimit(resource.RLIMIT_AS, (1 << 30, 1 << 30))
from shared.core.errors import InputError
from shared.render.camera_path import read_path_file
from shared.formats.ply import read_header
from shared.core.paths import read_bounded
for fn in (read_path_file, read_header, lambda p: read_bounded(p, p, 1 << 20)):
    for target in sys.argv[1:]:
        try:
            fn(target)
        except InputError as exc:
            print(exc.problem)
        else:
            print("READ")
"""


def test_a_job_names_no_worker_file_and_fifos_never_block(svc: Svc, tmp_path: Path, capture: Path) -> None:
    """``params.preview.path`` naming a FIFO, ``/dev/zero`` or any file is a 422 at submission;
    keyframes inline render. The readers that remain (a local --path file, a PLY, any bounded
    read) refuse a FIFO and /dev/zero at once, in a child under 1 GiB and 60 s."""
    fifo = tmp_path / "path.json"
    os.mkfifo(fifo)
    archive = jobsvc.capture_zip(capture, tmp_path / "cap.zip")
    for target in (str(fifo), "/dev/zero", str(capture / "capture.json")):
        code, doc = svc.submit(archive, params=json.dumps({"preview": {"path": target}}))
        assert code == 422, doc
        assert doc["detail"][0]["loc"] == ["body", "params", "preview", "path"], doc
    proc = subprocess.run([sys.executable, "-c", _READER, str(fifo), "/dev/zero"], capture_output=True, text=True,
                          timeout=60, env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])})
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.split("\n")[:-1] == ["is not a regular file"] * 6, proc.stdout
    # Inline keyframes: the preview renders (a target on its eye looks at the scene's centre).
    camera = {"fov": 45, "keyframes": [{"eye": [-40, 0, 0], "target": [-40, 0, 0]}, {"eye": [40, 0, 0], "target": [0, 0, 600]}]}
    params = json.dumps({"export": False, "preview": {"camera": camera, "size": [64, 48], "seconds": 0.5, "fps": 4}})
    job = svc.run(jobsvc.capture_zip(capture, tmp_path / "cap2.zip", note="inline"), params=params, timeout=240)
    assert job["state"] == "succeeded", job
    assert {"preview.mp4", "preview.png"} <= svc.artifacts(job), job


# ---- finding 8: store references ----------------------------------------------------------------------


def test_store_references_never_follow_links_out_of_the_store(svc: Svc, tmp_path: Path, capture: Path) -> None:
    """An inbox entry that is a link out of the store, or a referenced folder holding one, is
    refused at submission naming capture_ref, with one text whether the target exists or not."""
    inbox = Path(svc.senv.settings.storage_url) / "inbox"
    inbox.mkdir(parents=True, exist_ok=True)
    outside = tmp_path / "elsewhere"
    shutil.copytree(capture, outside)
    (inbox / "link_existing").symlink_to(outside)
    (inbox / "link_missing").symlink_to(tmp_path / "nothing-here")
    inner = inbox / "cap_with_link"
    shutil.copytree(capture, inner)
    (inner / "white.png").unlink()
    (inner / "white.png").symlink_to(outside / "white.png")
    texts = []
    for ref in ("inbox/link_existing", "inbox/link_missing", "inbox/cap_with_link"):
        r = svc.client.post("/v1/jobs", headers=svc.auth, json={"capture_ref": ref, "params": {"render": False}})
        assert r.status_code == 422, (ref, r.text)
        text = json.dumps(r.json())
        assert "capture_ref" in text and "inside the store" in text, text
        texts.append(text.replace(ref, "REF"))
    assert texts[0] == texts[1], texts
    # A folder inside the store is still a capture.
    shutil.copytree(capture, inbox / "good")
    r = svc.client.post("/v1/jobs", headers=svc.auth, json={"capture_ref": "inbox/good", "params": {"render": False}})
    assert r.status_code == 201, r.text


# ---- finding 9: numbers and sizes bounded at intake, errors that name the file ----------------------------


def _png(w: int, h: int) -> bytes:
    return cv2.imencode(".png", np.full((h, w), 128, np.uint8))[1].tobytes()


def test_numbers_and_sizes_refused_at_intake_naming_the_file(svc: Svc, tmp_path: Path, capture: Path) -> None:
    doc = json.loads((capture / "capture.json").read_text())
    # A 5000-digit integer in capture.json: the job's first stage names the file.
    text = json.dumps(doc).replace('"width": 64', '"width": ' + "9" * 5000, 1)
    job = svc.run(jobsvc.capture_zip(capture, tmp_path / "digits.zip", replace={"capture.json": text.encode()}))
    assert "capture.json: a number of 5000 characters (at most 40)" in _error(job)
    # A 1x1 capture fails at ingest naming the image, not at export with a store path.
    tiny = {p.name: _png(1, 1) for p in capture.glob("*.png")}
    job = svc.run(jobsvc.capture_zip(capture, tmp_path / "tiny.zip", replace=tiny))
    assert "white.png: image is 1x1" in _error(job)
    # A PLY header claiming 10^12 vertices: named, never an allocation of terabytes.
    big = b"ply\nformat ascii 1.0\nelement vertex 1000000000000\nproperty float x\nproperty float y\nproperty float z\nend_header\n0 0 0\n"
    ok = (_outside_ply(tmp_path / "o")).read_bytes()
    job = svc.run(_scanset_zip(tmp_path / "big.zip", {"format": "graylight-scanset-v1",
                                                       "views": [{"cloud": "big.ply"}, {"cloud": "ok.ply"}]},
                               {"big.ply": big, "ok.ply": ok}), "multiview")
    assert "views[0] (big): bad point cloud: big.ply: PLY header claims 1000000000000 vertices" in _error(job)
    # Job parameters and uploaded rigs: 422 before anything is stored.
    archive = jobsvc.capture_zip(capture, tmp_path / "p.zip", note="params")
    code, body = svc.submit(archive, params='{"tiles": {"max_chunk": 1e30}}')
    assert code == 422 and body["detail"][0]["loc"] == ["body", "params", "tiles", "max_chunk"], body
    rig = json.loads((capture / "rig.json").read_text())
    rig["camera"]["K"][0][0] = 1e308
    code, body = svc.submit(archive, rig=("rig.json", json.dumps(rig).encode(), "application/json"))
    assert code == 422 and "focal length" in json.dumps(body), body
    padded = json.dumps(json.loads((capture / "rig.json").read_text())).encode() + b" " * (1 << 20)
    code, body = svc.submit(archive, rig=("rig.json", padded, "application/json"))
    assert code == 422 and "too large" in json.dumps(body) and "malformed" not in json.dumps(body), body

