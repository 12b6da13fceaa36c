"""The scan graph's export stage: ``cloud.laz`` and ``cloud.copc.laz`` as job artifacts, read back
by laspy (and its COPC reader), with the triangulated cloud's every point."""

from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np

from shared.formats.ply import read_ply
from shared.service.artifacts import ArtifactStore, sha256_file
from shared.service.jobs import graph_for, stage_spec
from shared.service.jobstore import JobStore, NewJob
from tests.support.jobsvc import capture_zip, make_env
from workers.runner import run_stage


def test_export_stage_publishes_laz_and_copc(tmp_path: Path, small_capture: Path) -> None:
    assert stage_spec("scan", "export").publish == ("cloud.laz", "cloud.copc.laz")
    settings = make_env(tmp_path / "svc").settings
    store = JobStore(settings.database_url)
    owner, _ = store.create_key("t")
    arts = ArtifactStore(settings.storage_url, settings.s3_endpoint)
    archive = capture_zip(small_capture, tmp_path / "c.zip")
    key = sha256_file(archive)
    arts.put_files(key, {"capture.zip": archive})
    params = {"render": False}  # tiles and preview left out: the export needs only the cloud
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
    assert [s.name for s in job.stages] == ["ingest", "decode", "triangulate", "compress", "export"]
    cloud = read_ply(arts.fetch(job.stage("triangulate").output_key, tmp_path / "c1") / "cloud.ply")
    out = arts.fetch(job.stage("export").output_key, tmp_path / "c2")
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == [
        "cloud.copc.laz",
        "cloud.laz",
    ]
    las = laspy.read(out / "cloud.laz")
    assert las.header.point_count == len(cloud) > 1000
    xyz = np.stack([las.x, las.y, las.z], axis=1)
    assert np.abs(xyz - cloud.xyz).max() <= las.header.scales[0]
    with laspy.CopcReader.open(out / "cloud.copc.laz") as r:
        assert len(r.query()) == len(cloud)
