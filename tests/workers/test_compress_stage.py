"""The scan graph's compress stage: ``range.glr`` as a job artifact that decodes to the
triangulated range image (lossless at the quantum, or within the job's error bound), with the
raw ``range.npz`` published beside it or dropped by ``params.compress.keep_range``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from shared.compress.range import expected_lossless, read_range
from shared.core.errors import InputError
from shared.service.artifacts import ArtifactStore, detached_key
from shared.service.jobs import graph_for, stage_spec
from shared.service.params import check_job_params
from tests.support.inprocess import run_scan_job
from tests.support.jobsvc import make_env


def _run_job(tmp_path: Path, small_capture: Path, params: dict) -> tuple[ArtifactStore, object]:
    # Tiles and preview left out: compression needs only the range image.
    return run_scan_job(make_env(tmp_path / "svc").settings, small_capture, tmp_path, {"render": False, **params})


def _files(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if not p.name.startswith("."))


def test_compress_stage_lossless_keeps_the_raw_range(tmp_path: Path, small_capture: Path) -> None:
    assert "compress" in [s.name for s in graph_for("scan")]
    assert set(stage_spec("scan", "compress").publish) == {"range.glr", "range.npz", "compress.json"}
    arts, job = _run_job(tmp_path, small_capture, {})
    # The triangulation's range image is an object of its own (detached), kept with keep_range.
    raw = arts.fetch(detached_key(job.stage("triangulate").output_key, "range.npz"), tmp_path / "c1") / "range.npz"
    out = arts.fetch(job.stage("compress").output_key, tmp_path / "c2")
    assert _files(out) == ["compress.json", "range.glr", "range.npz"]
    assert (out / "range.npz").read_bytes() == raw.read_bytes()
    with np.load(raw) as d:
        z = d["z"]
    back = read_range(out / "range.glr").z
    m = ~np.isnan(z)
    assert m.sum() > 1000
    np.testing.assert_array_equal(np.isnan(back), ~m)
    np.testing.assert_array_equal(back[m], expected_lossless(z, 0.02)[m])
    assert job.stage("compress").summary["kept_range"] is True


def test_compress_stage_bounded_drops_the_raw_range(tmp_path: Path, small_capture: Path) -> None:
    # A job that keeps the range first, for the raw image to compare with (the second job reuses
    # its triangulation; tests/workers/test_keep_range.py follows the dropped object itself).
    arts, kept = _run_job(tmp_path, small_capture, {})
    raw = arts.fetch(kept.stage("compress").output_key, tmp_path / "c1") / "range.npz"
    arts, job = _run_job(tmp_path, small_capture, {"compress": {"max_error": 0.5, "keep_range": False}})
    out = arts.fetch(job.stage("compress").output_key, tmp_path / "c2")
    assert _files(out) == ["compress.json", "range.glr"]
    assert not arts.exists(detached_key(job.stage("triangulate").output_key, "range.npz"))
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


def _merge_output(folder: Path, points: int, views: int) -> Path:
    """A stand-in for the mv_merge stage's output: merged.ply (the fused dtype) and ranges/*.npz."""
    from shared.compress.range import RangeImage, save_range_npz
    from shared.formats.ply import write_ply_records
    from shared.merge.fusion import FUSED_DTYPE

    rng = np.random.default_rng(4)
    rec = np.zeros(points, FUSED_DTYPE)
    rec["x"], rec["y"] = rng.uniform(-50, 50, points), rng.uniform(-50, 50, points)
    rec["z"] = 600 + 0.1 * rec["x"] + rng.normal(0, 0.2, points)
    rec["red"] = rng.integers(0, 256, points)
    rec["nz"] = -1.0
    rec["size"] = 0.2
    rec["view"] = rng.integers(0, max(views, 1), points)
    rec["confidence"] = rng.random(points)
    folder.mkdir(parents=True)
    write_ply_records(folder / "merged.ply", iter([rec]), points, FUSED_DTYPE, ("units mm",))
    if views:
        (folder / "ranges").mkdir()
        yy, xx = np.mgrid[0:96, 0:128]
        for v in range(views):
            z = (700 + 0.3 * xx + 0.1 * yy + rng.normal(0, 0.2, xx.shape)).astype(np.float32)
            save_range_npz(folder / "ranges" / f"view_{v:02d}.npz", RangeImage(z, np.eye(3), np.zeros(5), "mm"))
    return folder


@pytest.mark.parametrize("points, views, kept", [(200_000, 2, "views"), (500, 3, "merged"), (5_000, 0, "merged")])
def test_multiview_compress_keeps_the_smaller(tmp_path: Path, points: int, views: int, kept: str) -> None:
    from shared.compress.cloud import decode_cloud
    from workers.stages import STAGE_FUNCS, StageContext

    assert [s.name for s in graph_for("multiview")].index("mv_compress") > [s.name for s in graph_for("multiview")].index("mv_merge")
    merged = _merge_output(tmp_path / "merge", points, views)
    out = tmp_path / "out"
    out.mkdir()
    ctx = StageContext(job_id="j", kind="multiview", stage="mv_compress", params={"compress": {"max_error": 0.1}},
                       capture_dir=None, inputs={"mv_merge": merged}, out_dir=out)
    summary = STAGE_FUNCS["mv_compress"](ctx)
    assert summary["kept"] == kept
    if views:
        assert (summary["views_bytes"] < summary["merged_bytes"]) == (kept == "views")
    if kept == "views":
        assert _files(out) == ["compress.json", "ranges"] and len(list((out / "ranges").glob("*.glr"))) == views
        back = read_range(out / "ranges" / "view_00.glr").z
        with np.load(merged / "ranges" / "view_00.npz") as d:
            assert np.abs(back.astype(np.float64) - d["z"]).max() <= 0.1
    else:
        assert _files(out) == ["compress.json", "merged.glo"]
        assert len(decode_cloud(out / "merged.glo")) == points
