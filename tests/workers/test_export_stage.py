"""The scan graph's export stage: ``cloud.laz``, ``cloud.copc.laz`` and ``cloud.e57`` as job artifacts,
read back by laspy (and its COPC reader) and pye57, with the triangulated cloud's every point."""

from __future__ import annotations

from pathlib import Path

import laspy
import numpy as np
import pye57

from shared.formats.ply import read_ply
from shared.service.jobs import stage_spec
from tests.support.inprocess import run_scan_job
from tests.support.jobsvc import make_env


def test_export_stage_publishes_laz_and_copc(tmp_path: Path, small_capture: Path) -> None:
    assert stage_spec("scan", "export").publish == ("cloud.laz", "cloud.copc.laz", "cloud.e57")
    # Tiles and preview left out: the export needs only the cloud.
    arts, job = run_scan_job(make_env(tmp_path / "svc").settings, small_capture, tmp_path, {"render": False})
    assert [s.name for s in job.stages] == ["ingest", "decode", "triangulate", "compress", "export", "publish"]
    cloud = read_ply(arts.fetch(job.stage("triangulate").output_key, tmp_path / "c1") / "cloud.ply")
    out = arts.fetch(job.stage("export").output_key, tmp_path / "c2")
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == [
        "cloud.copc.laz",
        "cloud.e57",
        "cloud.laz",
    ]
    las = laspy.read(out / "cloud.laz")
    assert las.header.point_count == len(cloud) > 1000
    xyz = np.stack([las.x, las.y, las.z], axis=1)
    assert np.abs(xyz - cloud.xyz).max() <= las.header.scales[0]
    with laspy.CopcReader.open(out / "cloud.copc.laz") as r:
        assert len(r.query()) == len(cloud)
    e57 = pye57.E57(str(out / "cloud.e57"))
    assert e57.get_header(0).point_count == len(cloud)
