"""The job service as a registrar and an operator use it (issue 24), against a real API process,
real worker processes, Redis and the job database: one scan capture and one scan set submitted
with ``graylight submit`` (the kind detected) into a named batch and followed to their end, and
a batch POSTed with a file that is not an archive. The finished jobs are shared by the module.

Each test names the defect of issue 24 it pins (each failed on the code before the fix)."""

from __future__ import annotations

import csv
import hashlib
import io
import json
import subprocess
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import pytest

from shared.service.jobstore import JobStore
from shared.service.queue import RERENDER_TASK, publisher
from shared.service.rerenders import RerenderStore
from tests.support import jobsvc, viewer_browser

# One group: under --dist loadgroup the module runs on one xdist worker, so the service run of
# ``finished`` (about 100 s of CPU, most of it the default derivatives) is made once, not once a worker.
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("job_links")]

#: Small previews: the tests are about the service, not the video.
PARAMS = {"preview": {"size": [96, 64], "seconds": 1, "fps": 4}}
BATCH = "museum a"


@dataclass
class Finished:
    senv: jobsvc.ServiceEnv
    url: str
    key: str
    env: dict[str, str]
    scan: str  # job ids
    multiview: str
    submit: subprocess.CompletedProcess
    batch: dict[str, Any]  # POST /v1/batches answer (a good archive and a non-archive)
    samples: list[dict[str, Any]] = field(default_factory=list)  # the scan set's job polled while it ran
    http: httpx.Client = field(default_factory=lambda: httpx.Client(timeout=60))  # one connection, kept alive

    @property
    def auth(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.key}"}

    def get(self, path: str, **kw: Any) -> httpx.Response:
        return self.http.get(f"{self.url}{path}", headers={**self.auth, **kw.pop("headers", {})}, **kw)

    def cli(self, *args: str, timeout: float = 120) -> subprocess.CompletedProcess:
        return subprocess.run([jobsvc.GRAYLIGHT, *args], env=self.env, capture_output=True, text=True, timeout=timeout)


def _final(f: Finished, job: str, timeout: float) -> dict[str, Any]:
    doc: dict[str, Any] = {}

    def done() -> bool:
        doc.update(f.get(f"/v1/jobs/{job}").json())
        return doc["state"] in ("succeeded", "failed", "cancelled")

    jobsvc.wait_for(done, timeout, f"job {job} final", interval=0.3)
    return doc


@pytest.fixture(scope="module")
def finished(tmp_path_factory: pytest.TempPathFactory, scanset_factory: Callable[..., Path]) -> Iterator[Finished]:
    root = tmp_path_factory.mktemp("links")
    with jobsvc.service_env(root) as senv, ThreadPoolExecutor(1) as pool:
        # The captures are simulated while the service's processes start.
        simulated = pool.submit(lambda: (jobsvc.simulate_small(root / "vase"),
                                         scanset_factory(views=8, size=(320, 240), projector=(256, 192))))
        _proc, url = jobsvc.start_api(senv)
        worker = jobsvc.start_worker(senv, "cpu,render", concurrency=2)
        capture, scanset = simulated.result()
        key = JobStore(senv.settings.database_url).create_key("registrar")[1]
        env = {**senv.env, "GRAYLIGHT_API_URL": url, "GRAYLIGHT_API_KEY": key}
        # The scan set's folder as a user has it: no --kind, scanset.json at its top.
        proc = subprocess.Popen([jobsvc.GRAYLIGHT, "submit", str(capture), str(scanset), "--batch", BATCH, "--wait",
                                 "--params", json.dumps(PARAMS), "--timeout", "900"],
                                env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip
        f = Finished(senv, url, key, env, "", "", None, {})  # type: ignore[arg-type]
        # Follow the scan set's job as a client polling it would, until submit --wait ends.
        ids: list[str] = []
        while proc.poll() is None:
            if len(ids) < 2:
                jobs = f.get("/v1/jobs", params={"batch": BATCH}).json()["jobs"]
                ids = [j["id"] for j in sorted(jobs, key=lambda j: j["created_at"])]
            if len(ids) == 2:
                doc = f.get(f"/v1/jobs/{ids[1]}").json()
                f.samples.append({"progress": doc["progress"],
                                  "running": [s["name"] for s in doc["stages"] if s["state"] == "running"]})  # fmt: skip
            time.sleep(0.25)
        out, err = proc.communicate()
        f.submit = subprocess.CompletedProcess(proc.args, proc.returncode, out, err)
        assert proc.returncode == 0, err[-3000:] + worker.text()[-3000:]
        f.scan, f.multiview = out.split()[:2]
        good = jobsvc.capture_zip(capture, root / "good.zip", note="registrar")
        files = [("captures", ("good.zip", good.read_bytes(), "application/zip")),
                 ("captures", ("notazip.zip", b"this is not an archive", "application/zip"))]  # fmt: skip
        r = httpx.post(f"{url}/v1/batches", headers=f.auth, files=files,
                       data={"name": "registrar 2", "params": json.dumps({"render": False})}, timeout=120)  # fmt: skip
        assert r.status_code == 201, r.text
        f.batch = r.json()
        for j in f.batch["jobs"]:
            assert _final(f, j, 300)["state"] == "succeeded"
        yield f
        f.http.close()


def _walk(f: Finished, answer: Any, seen: dict[str, int]) -> None:
    """Follow every URL in ``answer`` (a JSON answer; strings that are API paths or absolute
    URLs on the API), recording each status in ``seen``."""
    if isinstance(answer, dict):
        for k, v in answer.items():
            if k in ("url", "artifacts", "viewer") and isinstance(v, str) or isinstance(v, dict | list):
                _walk(f, v, seen)
            elif k in ("url", "viewer") and v is not None:
                raise AssertionError(f"{k} is not a string: {v!r}")
        return
    if isinstance(answer, list):
        for v in answer:
            _walk(f, v, seen)
        return
    if isinstance(answer, str) and (answer.startswith("/v1/") or answer.startswith("/viewer/") or answer.startswith(f.url)):
        path = answer[len(f.url):] if answer.startswith(f.url) else answer
        if path in seen:
            return
        r = f.get(path)
        seen[path] = r.status_code
        assert r.status_code == 200, f"{path}: {r.status_code} {r.text[:200]}"


def test_every_link_of_every_answer_resolves(finished: Finished) -> None:
    """Defect 2: artifact URLs were not URLs (``mv_decode#0/...``: the rest a fragment, 404)."""
    f = finished
    seen: dict[str, int] = {}
    for job in (f.scan, f.multiview, *f.batch["jobs"]):
        record = f.get(f"/v1/jobs/{job}").json()
        assert record["state"] == "succeeded"
        _walk(f, record, seen)
        _walk(f, f.get(f"/v1/jobs/{job}/artifacts").json(), seen)
    for batch in (BATCH, f.batch["id"]):
        b = f.get(f"/v1/batches/{batch}").json()
        for j in b["jobs"]:
            _walk(f, f.get(f"/v1/jobs/{j}").json(), seen)
        _walk(f, f.get(f"/v1/batches/{batch}/report.json").json(), seen)
        text = f.get(f"/v1/batches/{batch}/report.csv").text
        for row in csv.DictReader(io.StringIO(text)):
            _walk(f, row["artifacts"].split(), seen)
    encoded = [p for p in seen if "%23" in p]
    assert encoded and not any("#" in p for p in seen), "map-stage files must be listed, percent-encoded"
    assert any(p.endswith("/artifacts/cloud.e57") for p in seen) and any(p.startswith("/viewer/") for p in seen)
    # Ranges: the tiles the viewer reads, by the link the listing gives.
    arts = f.get(f"/v1/jobs/{f.multiview}/artifacts").json()["artifacts"]
    octree = next(a for a in arts if a["name"] == "tiles/octree.bin")
    r = f.get(octree["url"], headers={"Range": "bytes=10-99"})
    assert r.status_code == 206 and len(r.content) == 90
    print(f"followed {len(seen)} links, {len(encoded)} with an encoded '#'")


def test_submit_detects_the_kind_prints_the_batch_and_the_links(finished: Finished) -> None:
    """Defects 1, 3 and 5: a scan-set folder was refused without --kind (which --help did not
    list); submit --batch never printed the batch id; submit --wait ended with no link."""
    f = finished
    kinds = [f.get(f"/v1/jobs/{j}").json()["kind"] for j in (f.scan, f.multiview)]
    assert kinds == ["scan", "multiview"]
    batch = f.get(f"/v1/batches/{BATCH}").json()
    assert f"batch {batch['id']}" in f.submit.stderr
    for job in (f.scan, f.multiview):
        assert f"{f.url}/viewer/{job}#key={f.key}" in f.submit.stdout
        assert f"{f.url}/v1/jobs/{job}/artifacts/cloud.ply" in f.submit.stdout
    help_text = f.cli("submit", "--help").stdout
    assert all(k in help_text for k in ("scan", "multiview", "calibrate"))


def test_multiview_job_offers_what_a_scan_does(finished: Finished) -> None:
    """Defect 1: params.export was refused for a multiview job; cloud.laz, cloud.copc.laz and
    cloud.ply answered 404 for it."""
    f = finished
    record = f.get(f"/v1/jobs/{f.multiview}").json()
    links = {link["name"] for link in record["links"]}
    assert {"cloud.ply", "cloud.laz", "cloud.copc.laz", "cloud.e57", "preview.mp4", "compress.json"} <= links
    ply = f.get(f"/v1/jobs/{f.multiview}/artifacts/cloud.ply")
    assert ply.status_code == 200 and ply.content == f.get(f"/v1/jobs/{f.multiview}/artifacts/merged.ply").content
    schema = httpx.get(f"{f.url}/openapi.json").text
    assert '"false leaves out the LAZ / COPC / E57 export of the merged cloud"' in schema
    r = httpx.post(f"{f.url}/v1/jobs", headers=f.auth, json={"kind": "multiview", "capture_ref": "nowhere.zip",
                                                                "params": {"export": False, "tiles": {"max_leaf": 500}}})  # fmt: skip
    assert r.status_code == 404 and "nowhere.zip" in r.text  # the parameters passed; the reference did not


def test_a_batch_accounts_for_every_file(finished: Finished) -> None:
    """Defect 3: a rejected file vanished from GET /v1/batches/{id} and both reports; its
    ``jobs`` were always empty; a batch could not be named in the API or ``batch status``."""
    f = finished
    assert f.batch["rejected"] == [{"capture": "notazip.zip", "error": f.batch["rejected"][0]["error"]}]
    by_id = f.get(f"/v1/batches/{f.batch['id']}").json()
    by_name = f.get("/v1/batches/registrar 2").json()
    assert by_id == by_name
    assert by_id["total"] == 2 and by_id["counts"] == {"succeeded": 1, "rejected": 1} and by_id["progress"] == 1.0
    assert by_id["rejected"] == f.batch["rejected"] and "not a zip or tar" in by_id["rejected"][0]["error"]
    assert by_id["jobs"] == f.batch["jobs"] and by_id["jobs_total"] == 1
    rows = f.get(f"/v1/batches/{f.batch['id']}/report.json").json()["rows"]
    assert [(r["capture"], r["state"]) for r in rows] == [("good.zip", "succeeded"), ("notazip.zip", "rejected")]
    assert rows[1]["error"] == by_id["rejected"][0]["error"] and rows[1]["job"] is None
    table = list(csv.DictReader(io.StringIO(f.get(f"/v1/batches/{f.batch['id']}/report.csv").text)))
    assert [(t["capture"], t["state"], t["error"]) for t in table] == [(r["capture"], r["state"], r["error"] or "") for r in rows]
    # The submit's batch: its jobs listed, a page at a time.
    page = f.get(f"/v1/batches/{BATCH}", params={"jobs_limit": 1}).json()
    assert page["jobs"] == [f.scan] and page["jobs_total"] == 2 and page["jobs_next_offset"] == 1
    page = f.get(f"/v1/batches/{BATCH}", params={"jobs_limit": 1, "jobs_offset": 1}).json()
    assert page["jobs"] == [f.multiview] and page["jobs_next_offset"] is None
    r = f.cli("batch", "status", "registrar 2")
    assert r.returncode == 1 and "2 captures" in r.stdout and "rejected  notazip.zip" in r.stdout, r.stdout + r.stderr
    assert f.cli("batch", "status", BATCH).returncode == 0


def test_summaries_name_published_files_not_worker_paths(finished: Finished) -> None:
    """Defect 5: stage summaries exposed dead worker paths (``.../cache/work/preview-.../preview.mp4``)."""
    f = finished
    data_dir = f.senv.env["GRAYLIGHT_DATA_DIR"]
    for job in (f.scan, f.multiview):
        record = f.get(f"/v1/jobs/{job}").json()
        text = json.dumps([s["summary"] for s in record["stages"]])
        assert data_dir not in text and "/cache/" not in text, text[:500]
        preview = next(s for s in record["stages"] if s["name"] == "preview")
        assert "preview.mp4" in json.dumps(preview["summary"])


def test_job_show_download_and_view(finished: Finished, tmp_path: Path) -> None:
    """Defect 5: the CLI could not show one job or download its artifacts; no command opened
    local results (the viewer's ?tiles= on them failed: another origin, no CORS)."""
    f = finished
    r = f.cli("job", "show", f.multiview)
    assert r.returncode == 0 and f"{f.url}/viewer/{f.multiview}#key=" in r.stdout and "mv_merge" in r.stdout
    r = f.cli("job", "download", f.multiview, "--artifact", "cloud.ply", "--artifact", "tiles", "--out", str(tmp_path / "mv"))
    assert r.returncode == 0, r.stderr
    listing = {a["name"]: a for a in f.get(f"/v1/jobs/{f.multiview}/artifacts").json()["artifacts"]}
    got = {p.relative_to(tmp_path / "mv").as_posix() for p in (tmp_path / "mv").rglob("*") if p.is_file()}
    assert got == {"cloud.ply"} | {n for n in listing if n.startswith("tiles/")}
    assert hashlib.sha256((tmp_path / "mv" / "cloud.ply").read_bytes()).hexdigest() == listing["cloud.ply"]["sha256"]
    assert f.cli("view", f.multiview).stdout.strip() == f"{f.url}/viewer/{f.multiview}#key={f.key}"
    # The viewer page reads the job's artifact list, whose name titles the page (not the job's id).
    page = httpx.get(f"{f.url}/viewer/{f.multiview}").text
    config = json.loads(page.split('id="graylight-config" type="application/json">', 1)[1].split("</script>", 1)[0])
    assert f.get(config["artifacts"]).json()["name"].startswith("scanset-")
    listing_page = f.cli("jobs", "--batch", BATCH, "--limit", "1")
    assert listing_page.stdout.split()[0] == f.multiview and "--offset 1" in listing_page.stderr

    port = jobsvc.free_port()
    view = subprocess.Popen([jobsvc.GRAYLIGHT, "view", str(tmp_path / "mv"), "--port", str(port)], env=f.env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)  # fmt: skip
    try:
        line = view.stdout.readline().strip()
        assert line == f"http://127.0.0.1:{port}/"

        def up() -> bool:
            try:
                return httpx.get(line, timeout=1).status_code in (200, 307)
            except httpx.HTTPError:
                return False

        jobsvc.wait_for(up, 30, "graylight view up")
        page = httpx.get(line, follow_redirects=True, timeout=10)
        assert page.status_code == 200
        query = httpx.URL(str(page.url)).params
        assert query["name"] == "mv" and query["tiles"] == "/results/tiles/"
        meta = httpx.get(f"{line.rstrip('/')}{query['tiles']}metadata.json", timeout=10)
        assert meta.status_code == 200 and meta.json()["points"] > 0
        part = httpx.get(f"{line.rstrip('/')}{query['tiles']}octree.bin", headers={"Range": "bytes=0-63"}, timeout=10)
        assert part.status_code == 206 and len(part.content) == 64
        # In a browser: the local results load (no "Failed to fetch"), and the job's page is
        # titled with the job's name.
        name = f.get(f"/v1/jobs/{f.multiview}").json()["name"]
        with viewer_browser.chromium() as browser:
            local = viewer_browser.Page(browser, line)
            state = local.wait_idle()
            assert state.get("error") in (None, "") and not local.errors, (state, local.errors)
            assert local.page.title() == "mv · Graylight"
            job_page = viewer_browser.Page(browser, f"{f.url}/viewer/{f.multiview}#key={f.key}")
            job_page.wait_idle()
            job_page.page.wait_for_function("(n) => document.title.startsWith(n)", arg=name, timeout=10_000)
            assert job_page.page.title() == f"{name} · Graylight" and not job_page.errors, job_page.errors
    finally:
        view.terminate()
        view.wait(timeout=10)


def test_progress_follows_the_work(finished: Finished) -> None:
    """Defect 6: the job's progress counted stages, so a multi-view job sat at one value through
    its whole merge. Now each stage's own fraction moves the job by the stage's share."""
    for job in (finished.scan, finished.multiview):
        stages = finished.get(f"/v1/jobs/{job}").json()["stages"]
        print("stage seconds:", {s["name"]: round(s["seconds"] or 0, 2) for s in stages})
    during = [s["progress"] for s in finished.samples if s["running"] == ["mv_merge"]]
    assert len(during) >= 3, finished.samples
    ups = [b - a for a, b in zip(during, during[1:], strict=False)]
    assert all(u >= 0 for u in ups)
    assert sum(1 for u in ups if u > 0) >= 2, during  # it moved while the merge ran
    assert max(during) - min(during) > 0.1, during  # by the merge's share, not a twentieth of the stages
    progress = [s["progress"] for s in finished.samples]
    assert all(b >= a - 1e-9 for a, b in zip(progress, progress[1:], strict=False)), progress


def test_the_nightly_rerender_is_not_seen_by_a_client(finished: Finished) -> None:
    """Defect 4: a forced re-render of all flipped finished jobs to running for tens of seconds,
    overwrote finished_at and counted a second attempt. Now it runs beside the jobs; the new
    preview replaces the old at once; the mode comes from beat's message."""
    f = finished
    jobs = [f.scan, f.multiview]
    before = {j: f.get(f"/v1/jobs/{j}").json() for j in jobs}
    old = {j: hashlib.sha256(f.get(f"/v1/jobs/{j}/artifacts/preview.mp4").content).hexdigest() for j in jobs}
    # What beat sends at GRAYLIGHT_RERENDER_HOUR with GRAYLIGHT_RERENDER_MODE=all.
    publisher(f.senv.settings).send_task(RERENDER_TASK, args=["all"], queue=f.senv.settings.queue("control"))
    served: dict[str, set[str]] = {j: set() for j in jobs}
    states: set[str] = set()

    def done() -> bool:
        finished_all = True
        for j in jobs:
            doc = f.get(f"/v1/jobs/{j}").json()
            states.add(doc["state"])
            assert doc["finished_at"] == before[j]["finished_at"]
            assert [(s["name"], s["state"], s["attempts"], s["finished_at"]) for s in doc["stages"]] == [
                (s["name"], s["state"], s["attempts"], s["finished_at"]) for s in before[j]["stages"]]
            video = f.get(f"/v1/jobs/{j}/artifacts/preview.mp4")
            assert video.status_code == 200
            served[j].add(hashlib.sha256(video.content).hexdigest())
            rr = doc["rerender"]
            finished_all &= rr is not None and rr["state"] in ("succeeded", "failed")
        return finished_all

    jobsvc.wait_for(done, 300, "re-renders done", interval=0.2)
    assert states == {"succeeded"}
    for j in jobs:
        doc = f.get(f"/v1/jobs/{j}").json()
        assert doc["rerender"]["state"] == "succeeded" and doc["rerender"]["reason"] == "nightly-all", doc["rerender"]
        arts = {a["name"]: a for a in f.get(f"/v1/jobs/{j}/artifacts").json()["artifacts"]}
        new = hashlib.sha256(f.get(f"/v1/jobs/{j}/artifacts/preview.mp4").content).hexdigest()
        assert new == arts["preview.mp4"]["sha256"]
        assert served[j] <= {old[j], new}  # the old video or the new one, never anything else
        preview_before = next(s for s in before[j]["stages"] if s["name"] == "preview")
        preview_now = next(s for s in doc["stages"] if s["name"] == "preview")
        assert preview_now["attempts"] == preview_before["attempts"]
    store = JobStore(f.senv.settings.database_url)
    for j in jobs:
        assert not [e for e in store.events(j) if e[0] is None and e[1] == "succeeded"]  # the job never left succeeded


def test_rerender_by_hand_and_a_failed_one_leaves_the_job(finished: Finished) -> None:
    """Defect 4: there was no way to re-render one job or a batch by hand; a failure is
    reported on the re-render alone."""
    f = finished
    r = f.cli("rerender", "--batch", BATCH)
    assert r.returncode == 0 and sorted(r.stdout.split()) == sorted([f.scan, f.multiview]), r.stdout + r.stderr
    again = httpx.post(f"{f.url}/v1/jobs/{f.scan}/rerender", headers=f.auth)
    assert again.status_code in (202, 409)  # 409 while the batch's re-render of it is under way

    def settled(j: str) -> dict:
        doc = f.get(f"/v1/jobs/{j}").json()
        return doc if doc["rerender"]["state"] in ("succeeded", "failed") else {}

    for j in (f.scan, f.multiview):
        jobsvc.wait_for(lambda j=j: settled(j), 300, f"re-render of {j}", interval=0.3)
    # A re-render that cannot succeed (a preview size no renderer accepts) fails alone.
    store = JobStore(f.senv.settings.database_url)
    job = store.get_job(f.scan)
    before = f.get(f"/v1/jobs/{f.scan}").json()
    old = f.get(f"/v1/jobs/{f.scan}/artifacts/preview.mp4").content
    rec = RerenderStore(store).create_rerender(job.id, {**job.params, "preview": {"size": [7, 7]}}, "manual")
    assert rec is not None
    from shared.service.queue import publish_rerender

    publish_rerender(rec.id, f.senv.settings)
    doc = jobsvc.wait_for(lambda: settled(f.scan), 120, "the bad re-render to end", interval=0.2)
    assert doc["rerender"]["state"] == "failed" and "size" in doc["rerender"]["error"], doc["rerender"]
    assert doc["state"] == "succeeded" and doc["finished_at"] == before["finished_at"] and doc["error"] is None
    assert f.get(f"/v1/jobs/{f.scan}/artifacts/preview.mp4").content == old
