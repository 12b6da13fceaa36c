"""The scan graph's compress stage: ``range.glr`` as a job artifact that decodes to the
triangulated range image (lossless at the quantum, or within the job's error bound), with the
raw ``range.npz`` published beside it or dropped by ``params.compress.keep_range``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from shared.compress.range import expected_lossless, read_range
from shared.core.errors import InputError
from shared.service.artifacts import ArtifactStore, sha256_file
from shared.service.jobs import graph_for, stage_spec
from shared.service.jobstore import JobStore, NewJob
from shared.service.params import check_job_params
from tests.support.jobsvc import capture_zip, make_env
from workers.runner import run_stage


def _run_job(tmp_path: Path, small_capture: Path, params: dict) -> tuple[ArtifactStore, object]:
    settings = make_env(tmp_path / "svc").settings
    store = JobStore(settings.database_url)
    owner, _ = store.create_key("t")
    arts = ArtifactStore(settings.storage_url, settings.s3_endpoint)
    archive = capture_zip(small_capture, tmp_path / "c.zip")
    key = sha256_file(archive)
    arts.put_files(key, {"capture.zip": archive})
    params = {"render": False, **params}  # tiles and preview left out: compression needs only the range image
    job, _ = store.create_job(owner.id, NewJob(kind="scan", capture_ref=f"object:{key}", capture_key=key,
                                               graph=graph_for("scan", params), name="c.zip", params=params))  # fmt: skip
    for _ in range(10):
        job = store.get_job(job.id)
        if job.state in ("succeeded", "failed", "cancelled"):
            break
        for st in job.stages:
            if st.state == "queued":
                run_stage(st.id, settings, publish=False)
    assert job.state == "succeeded", job
    return arts, job


def _files(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if not p.name.startswith("."))


def test_compress_stage_lossless_keeps_the_raw_range(tmp_path: Path, small_capture: Path) -> None:
    assert "compress" in [s.name for s in graph_for("scan")]
    assert set(stage_spec("scan", "compress").publish) == {"range.glr", "range.npz", "compress.json"}
    arts, job = _run_job(tmp_path, small_capture, {})
    raw = arts.fetch(job.stage("triangulate").output_key, tmp_path / "c1") / "range.npz"
    out = arts.fetch(job.stage("compress").output_key, tmp_path / "c2")
    assert _files(out) == ["compress.json", "range.glr", "range.npz"]
    with np.load(raw) as d:
        z = d["z"]
    back = read_range(out / "range.glr").z
    m = ~np.isnan(z)
    assert m.sum() > 1000
    np.testing.assert_array_equal(np.isnan(back), ~m)
    np.testing.assert_array_equal(back[m], expected_lossless(z, 0.02)[m])
    assert job.stage("compress").summary["kept_range"] is True


def test_compress_stage_bounded_drops_the_raw_range(tmp_path: Path, small_capture: Path) -> None:
    arts, job = _run_job(tmp_path, small_capture, {"compress": {"max_error": 0.5, "keep_range": False}})
    raw = arts.fetch(job.stage("triangulate").output_key, tmp_path / "c1") / "range.npz"
    out = arts.fetch(job.stage("compress").output_key, tmp_path / "c2")
    assert _files(out) == ["compress.json", "range.glr"]
    with np.load(raw) as d:
        z = d["z"]
    back = read_range(out / "range.glr").z
    m = ~np.isnan(z)
    np.testing.assert_array_equal(np.isnan(back), ~m)
    assert np.abs(back[m].astype(np.float64) - z[m]).max() <= 0.5
    summary = job.stage("compress").summary
    assert summary["kept_range"] is False and summary["mode"] == "bounded"


@pytest.mark.parametrize("value, field", [
    ({"max_error": 0}, "params.compress.max_error"),
    ({"quantum": -1}, "params.compress.quantum"),
    ({"quantum": 0.1, "max_error": 0.1}, "params.compress"),
    ({"keep_range": "no"}, "params.compress.keep_range"),
    ({"level": 3}, "params.compress"),
])  # fmt: skip
def test_bad_compress_params_are_refused_at_the_edge(value: dict, field: str) -> None:
    with pytest.raises(InputError, match=rf"^{field}: "):
        check_job_params("scan", {"compress": value})
