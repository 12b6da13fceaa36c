"""The scan pipeline: stage functions and the embedded whole write complete, consistent outputs."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from shared.core.errors import InputError
from shared.formats.ply import read_header, read_ply
from shared.formats.rig import load_rig, save_rig
from shared.scan.pipeline import decode_stage, ingest_stage, scan, triangulate_stage
from tests.support.synthetic_plane import PlaneTruth, render_plane_capture


@pytest.fixture(scope="module")
def small(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, PlaneTruth]:
    out = tmp_path_factory.mktemp("pipe") / "capture"
    return out, render_plane_capture(out, (240, 180), (64, 48), seed=3)


def test_scan_writes_cloud_range_and_report(tmp_path: Path, small) -> None:
    root, truth = small
    seen: list[float] = []
    out = tmp_path / "out"
    report = scan(root, out, progress=seen.append)
    assert sorted(p.name for p in out.iterdir()) == ["cloud.ply", "range.npz", "report.json"]
    assert seen[-1] == 1.0 and all(b >= a for a, b in zip(seen, seen[1:], strict=False))
    on_disk = json.loads((out / "report.json").read_text())
    assert on_disk == json.loads(json.dumps(report))
    for key in ("ingest", "decode", "triangulate", "write", "total"):
        assert report["seconds"][key] >= 0
    assert report["decode"]["lit_pixels"] > 0 and report["decode"]["column_decoded"] > 0
    header = read_header(out / "cloud.ply")
    assert header.fmt == "binary_little_endian"
    assert list(header.dtype.names) == ["x", "y", "z", "red", "green", "blue", "nx", "ny", "nz", "size"]
    cloud = read_ply(out / "cloud.ply")
    assert len(cloud) == report["points"] >= 0.98 * truth.lit.sum()
    assert np.sqrt(np.mean(truth.distance(cloud.xyz) ** 2)) < 2.0
    with np.load(out / "range.npz") as z:
        rng = z["z"]
        assert rng.shape == (180, 240) and rng.dtype == np.float32
        assert np.isfinite(rng).sum() == report["points"]
        np.testing.assert_allclose(z["K"], truth.rig.camera.K)
        assert str(z["units"]) == "mm"
    np.testing.assert_allclose(np.sort(rng[np.isfinite(rng)]), np.sort(cloud.xyz[:, 2]))


def test_stages_chain_like_the_job_service(tmp_path: Path, small) -> None:
    root, _ = small
    cap = ingest_stage(root)
    assert cap.rig == root / "rig.json"
    stats = decode_stage(root, tmp_path / "work")
    assert (tmp_path / "work" / "decoded.npz").is_file() and stats["lit_pixels"] > 0
    part = triangulate_stage(tmp_path / "work" / "decoded.npz", root / "rig.json", tmp_path / "tri")
    assert (tmp_path / "tri" / "cloud.ply").is_file() and (tmp_path / "tri" / "range.npz").is_file()
    whole = scan(root, tmp_path / "whole")
    assert part["points"] == whole["points"]
    assert json.loads((tmp_path / "tri" / "triangulate.json").read_text())["points"] == part["points"]


def test_ingest_rejects_mixed_sizes_and_mismatched_rigs(tmp_path: Path, small) -> None:
    root, truth = small
    broken = tmp_path / "cap"
    shutil.copytree(root, broken)
    cv2.imwrite(str(broken / "col_02.png"), np.zeros((100, 120), np.uint8))
    with pytest.raises(InputError, match="mixed image sizes") as exc:
        ingest_stage(broken)
    assert "col_02.png" in str(exc.value)
    # A rig for another camera: named in the message, before any decoding.
    other = tmp_path / "other-rig.json"
    save_rig(
        load_rig(root / "rig.json").__class__(
            camera=truth.rig.camera.__class__(640, 480, truth.rig.camera.K, truth.rig.camera.dist),
            projector=truth.rig.projector,
            R=truth.rig.R,
            T=truth.rig.T,
        ),
        other,
    )
    with pytest.raises(InputError, match="rig camera is 640x480 but the images are 240x180"):
        ingest_stage(root, rig=other)
    with pytest.raises(InputError, match="rig camera"):
        scan(root, tmp_path / "never", rig=other)
    assert not (tmp_path / "never").exists()


def test_scan_of_a_simulated_colour_16bit_capture(tmp_path: Path, sim_capture_factory) -> None:
    """16-bit colour images (the virtual rig's spheres, with specular highlights) against truth."""
    from shared.sim.simulate import load_truth

    # A linear camera: under the virtual rig's default sRGB response this decoder, whose thresholds
    # are in stored values, accepts more dark pixels (99.93 % of lit pixels against 99.64 %, RMS
    # 0.82 mm against 0.86 mm) and 0.223 % of its points are more than 5 mm off (0.163 % linear).
    root = sim_capture_factory("spheres", size=(480, 360), seed=2, colour=True, bits=16, response="linear")
    assert cv2.imread(str(root / "col_00.png"), cv2.IMREAD_UNCHANGED).dtype == np.uint16
    report = scan(root, tmp_path / "out")
    truth = load_truth(root)
    cloud = read_ply(tmp_path / "out" / "cloud.ply")
    with np.load(tmp_path / "out" / "range.npz") as z:
        rng = z["z"]
    ys, xs = np.nonzero(np.isfinite(rng))
    assert len(xs) == len(cloud) == report["points"]
    # Points are written in pixel order (row-major), the order of the range image's valid pixels.
    np.testing.assert_array_equal(cloud.xyz[:, 2], rng[ys, xs])
    assert np.count_nonzero(truth.lit[ys, xs]) >= 0.98 * np.count_nonzero(truth.lit)
    P, N = truth.points[ys, xs].astype(np.float64), truth.normals[ys, xs].astype(np.float64)
    dist = np.abs(np.einsum("ij,ij->i", cloud.xyz - P, N))
    dist = np.where(np.isfinite(dist), dist, np.inf)
    assert np.mean(dist > 5) <= 0.002
    assert np.sqrt(np.mean(dist[dist <= 5] ** 2)) < 1.0
    # Colour comes through: the spheres are not grey.
    assert np.abs(cloud.rgb.astype(int) - cloud.rgb.mean(axis=1, keepdims=True)).mean() > 3


def test_failure_while_writing_leaves_nothing(tmp_path: Path, small, monkeypatch: pytest.MonkeyPatch) -> None:
    import shared.scan.pipeline as pipeline

    root, _ = small

    def disk_full(path: Path, *args: object) -> None:
        Path(path).write_bytes(b"partial")
        raise OSError("No space left on device")

    monkeypatch.setattr(pipeline, "_save_range_atomic", disk_full)
    out = tmp_path / "out"
    with pytest.raises(OSError, match="No space"):
        scan(root, out)
    assert list(out.iterdir()) == []  # the cloud written before the failure is gone too
