"""OpenCV FileStorage stereo calibrations <-> rig.json: both namings, round trips, sizes, bad files."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from services.cli.main import main
from shared.calib.session import write_opencv_yaml
from shared.core.errors import InputError
from shared.formats.opencv_rig import read_opencv_rig, write_opencv_rig
from shared.formats.rig import Device, Rig, load_rig, save_rig


def _rig(units: str = "mm") -> Rig:
    R = cv2.Rodrigues(np.array([0.02, -0.31, 0.015]))[0]
    cam = Device(1280, 1024, np.array([[3452.4, 0.0, 587.2], [0.0, 3449.9, 521.4], [0.0, 0.0, 1.0]]),
                 np.array([-0.222, -0.866, -7.3e-4, -1.7e-3, 3.125]))  # fmt: skip
    proj = Device(1024, 768, np.array([[2100.0, 0.0, 512.5], [0.0, 2101.5, 700.1], [0.0, 0.0, 1.0]]),
                  np.array([0.01, -0.02, 0.0, 0.0, 0.0]))  # fmt: skip
    return Rig(camera=cam, projector=proj, R=R, T=np.array([212.3, -3.1, 40.2]), units=units)


def _same(a: Rig, b: Rig) -> None:
    for da, db in ((a.camera, b.camera), (a.projector, b.projector)):
        assert (da.width, da.height) == (db.width, db.height)
        assert np.allclose(da.K, db.K, rtol=1e-15) and np.allclose(da.dist, db.dist, rtol=1e-15)
    assert np.allclose(a.R, b.R, rtol=1e-15, atol=1e-15) and np.allclose(a.T, b.T, rtol=1e-15)
    assert a.units == b.units


@pytest.mark.parametrize("naming", ["graylight", "stereo"])
def test_round_trip_both_namings(naming: str, tmp_path: Path) -> None:
    rig = _rig("cm")
    path = write_opencv_rig(rig, tmp_path / "calib.yaml", naming)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)  # OpenCV itself reads it
    key = "K1" if naming == "stereo" else "camera_matrix"
    assert np.allclose(fs.getNode(key).mat(), rig.camera.K)
    fs.release()
    _same(read_opencv_rig(path), rig)


def test_reads_what_calibrate_export_opencv_writes(tmp_path: Path) -> None:
    rig = _rig()
    path = write_opencv_yaml(tmp_path / "session.yaml", rig=rig, extra={"rms_stereo": 0.31})
    _same(read_opencv_rig(path), rig)


def _stereo_calibrate_file(path: Path, rig: Rig, **extra) -> Path:
    """What a stereoCalibrate user typically saves: K1 D1 K2 D2 R T (and maybe E, F), no sizes."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("K1", rig.camera.K)
    fs.write("D1", rig.camera.dist.reshape(1, -1))
    fs.write("K2", rig.projector.K)
    fs.write("D2", rig.projector.dist[:4].reshape(1, -1))
    fs.write("R", rig.R)
    fs.write("T", rig.T.reshape(3, 1))
    fs.write("E", np.eye(3))
    for k, v in extra.items():
        fs.write(k, v)
    fs.release()
    return path


def test_stereo_file_without_sizes_needs_flags(tmp_path: Path) -> None:
    rig = _rig()
    path = _stereo_calibrate_file(tmp_path / "stereo.yml", rig)
    with pytest.raises(InputError, match="--camera-size"):
        read_opencv_rig(path)
    got = read_opencv_rig(path, camera_size=(1280, 1024), projector_size=(1024, 768))
    assert got.projector.dist.shape == (5,) and got.projector.dist[4] == 0
    assert np.allclose(got.T, rig.T) and got.units == "mm"
    with pytest.raises(InputError, match="--camera-size"):  # disagrees with the file's own size
        read_opencv_rig(_stereo_calibrate_file(tmp_path / "s2.yml", rig, imageSize=np.array([[640.0], [480.0]])),
                        camera_size=(1280, 1024), projector_size=(1024, 768))  # fmt: skip


def test_image_size_keys_and_xml(tmp_path: Path) -> None:
    rig = _rig()
    path = _stereo_calibrate_file(tmp_path / "stereo.xml", rig, image_width=1280, image_height=1024,
                                  image_width2=1024, image_height2=768)  # fmt: skip
    got = read_opencv_rig(path)
    assert (got.camera.width, got.camera.height, got.projector.width, got.projector.height) == (
        1280,
        1024,
        1024,
        768,
    )


@pytest.mark.parametrize(
    ("edit", "needle"),
    [
        ({"drop": "K2"}, 'missing field "K2"'),
        ({"drop": "T"}, 'missing field "T"'),
        ({"K1": np.eye(2)}, 'field "K1" has shape'),
        ({"K1": np.array([[-5.0, 0, 1], [0, 5, 1], [0, 0, 1]])}, 'field "K1" is not a camera matrix'),
        ({"D1": np.zeros((1, 6))}, 'field "D1"'),
        ({"R": np.diag([1.0, 1.0, 2.0])}, 'field "R" is not a rotation'),
        ({"T": np.zeros((3, 1))}, 'field "T" is zero'),
        ({"T": np.zeros((2, 1)) + 1}, 'field "T" has shape'),
        ({"image_width": -3, "image_height": 10}, 'field "image_width"'),
    ],
)
def test_bad_fields_name_the_field(edit: dict, needle: str, tmp_path: Path) -> None:
    rig = _rig()
    values = {"K1": rig.camera.K, "D1": rig.camera.dist.reshape(1, -1), "K2": rig.projector.K,
              "D2": rig.projector.dist.reshape(1, -1), "R": rig.R, "T": rig.T.reshape(3, 1)}  # fmt: skip
    drop = edit.pop("drop", None)
    values.update(edit)
    values.pop(drop, None)
    path = tmp_path / "bad.yaml"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for k, v in values.items():
        fs.write(k, v)
    fs.release()
    with pytest.raises(InputError, match=needle) as err:
        read_opencv_rig(path, camera_size=(1280, 1024), projector_size=(1024, 768))
    assert "\n" not in str(err.value) and str(path) in str(err.value)


def test_not_a_filestorage(tmp_path: Path) -> None:
    junk = tmp_path / "junk.yaml"
    junk.write_text("this: [is, not\n  closed")
    with pytest.raises(InputError, match="junk.yaml") as err:
        read_opencv_rig(junk)
    # OpenCV's message names its build's source file: only the parser's words are kept
    assert ".cpp" not in str(err.value) and "/io/" not in str(err.value), str(err.value)
    assert str(err.value).endswith("(Parsing error at line 2: Missing , between the elements)"), str(err.value)
    plain = tmp_path / "plain.yaml"
    plain.write_text("%YAML:1.0\n---\nfoo: 1\n")
    with pytest.raises(InputError, match='"K1"'):
        read_opencv_rig(plain)
    with pytest.raises(InputError, match="not found"):
        read_opencv_rig(tmp_path / "nope.yaml")


def test_cli_import_export(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rig = _rig()
    save_rig(rig, tmp_path / "rig.json")
    assert (
        main(
            [
                "rig",
                "export",
                str(tmp_path / "rig.json"),
                "--out",
                str(tmp_path / "k.yaml"),
                "--naming",
                "stereo",
            ]
        )
        == 0
    )
    assert main(["rig", "import", str(tmp_path / "k.yaml"), "--out", str(tmp_path / "back.json")]) == 0
    _same(load_rig(tmp_path / "back.json"), rig)
    stereo = _stereo_calibrate_file(tmp_path / "s.yaml", rig)
    capsys.readouterr()
    assert main(["rig", "import", str(stereo), "--out", str(tmp_path / "x.json")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--projector-size" in err or "--camera-size" in err
    assert not (tmp_path / "x.json").exists()
    assert main(["rig", "import", str(stereo), "--out", str(tmp_path / "x.json"), "--camera-size", "1280x1024",
                 "--projector-size", "1024x768", "--units", "m"]) == 0  # fmt: skip
    assert load_rig(tmp_path / "x.json").units == "m"


def test_reads_the_real_procam_calibration() -> None:
    """The calibration committed with the real session (its own tool's naming, XML): the data
    README gives its camera as 1280x1024 with fx about 3452, cx about 587, cy about 521."""
    from shared.core.datapaths import shared_data_dir

    path = shared_data_dir() / "procam-kamino410" / "calibration_result.xml"
    with pytest.raises(InputError, match="--projector-size"):
        read_opencv_rig(path)  # the file has no projector size
    rig = read_opencv_rig(path, projector_size=(1024, 768))
    assert (rig.camera.width, rig.camera.height) == (1280, 1024)
    assert rig.camera.fx == pytest.approx(3452, abs=1) and rig.camera.cx == pytest.approx(587, abs=1)
    assert rig.camera.cy == pytest.approx(521, abs=1)
    assert (rig.projector.width, rig.projector.height) == (1024, 768)
    assert np.allclose(rig.R @ rig.R.T, np.eye(3), atol=1e-6)
