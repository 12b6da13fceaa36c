"""Stereo calibrations as OpenCV FileStorage files (YAML or XML), to and from ``rig.json``.

Two namings are read (and written):

- ``graylight`` (what ``graylight calibrate --export-opencv`` writes): ``camera_matrix``,
  ``camera_distortion``, ``projector_matrix``, ``projector_distortion``, ``R``, ``T``, with
  ``camera_width``/``camera_height``, ``projector_width``/``projector_height`` and ``units``;
- ``stereo`` (what ``cv2.stereoCalibrate`` users save): ``K1``, ``D1`` (the camera), ``K2``,
  ``D2`` (the projector, or the second camera), ``R``, ``T``;
- ``procam`` (read only: the structured-light calibration tool whose result ships with
  ``procam-kamino410``): ``cam_int``, ``cam_dist``, ``proj_int``, ``proj_dist``, ``roration``
  (sic; ``rotation`` accepted), ``translation``, and the camera's ``img_shape`` = [rows, cols].

``R``/``T`` map the first device's frame to the second's (``X_2 = R X_1 + T``, OpenCV's
convention and rig.json's). Image sizes come from the file when present (the ``*_width`` /
``*_height`` keys above, ``image_width``/``image_height`` or ``imageSize``/``image_size``
= [w, h] for the first device, the same with a ``2`` suffix for the second), else from the
caller (the CLI's ``--camera-size``/``--projector-size``). OpenCV files carry no unit; the
``units`` key is read when there, else the caller's (default mm).

Bad files raise :class:`~shared.core.errors.InputError` naming the file and the field as the
file spells it.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import cv2
import numpy as np

from shared.core.errors import InputError
from shared.core.files import atomic_file
from shared.formats.rig import Device, Rig, parse_rig

NAMINGS = {
    "graylight": ("camera_matrix", "camera_distortion", "projector_matrix", "projector_distortion"),
    "stereo": ("K1", "D1", "K2", "D2"),
}
#: Namings read (not written): the same four keys.
READ_NAMINGS = {**NAMINGS, "procam": ("cam_int", "cam_dist", "proj_int", "proj_dist")}
#: Rotation and translation keys of each naming, the first present is read.
_RT_KEYS = {"procam": (("roration", "rotation"), ("translation",))}
_RT_DEFAULT = (("R",), ("T",))
_SIZE_KEYS = {
    1: (("camera_width", "camera_height"), ("image_width", "image_height"), ("imageSize",), ("image_size",)),
    2: (("projector_width", "projector_height"), ("image_width2", "image_height2"), ("imageSize2",), ("image_size2",)),
}  # fmt: skip
_DIST_SIZES = (4, 5, 8, 12, 14)


def _parser_message(line: str) -> str:
    """What OpenCV's parser says, without its build's source paths: ``OpenCV(5.1.0)
    /io/opencv/modules/core/src/persistence_yml.cpp:684: error: (-212:Parsing error) parseValue
    in function '/path/calib.yaml(2): Missing , between the elements'`` reads ``Parsing error at
    line 2: Missing , between the elements``."""
    m = re.search(r"error: \(-?\d+:([^)]*)\)\s*(.*?)(?:\s+in function '(.*)')?$", line)
    if not m:
        return "parse error" if ".cpp" in line or "/" in line else line
    kind, where, detail = m.group(1), m.group(2), m.group(3) or ""
    at = re.search(r"\((\d+)\):\s*(.+)$", detail)
    if at:
        return f"{kind} at line {at.group(1)}: {at.group(2)}"
    return f"{kind}: {where}" if where else kind


def _open(path: Path) -> cv2.FileStorage:
    if not path.is_file():
        raise InputError(path, "calibration file not found")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:  # OpenCV's parser errors surface as either
        cause = exc.__cause__ or exc.__context__ or exc
        lines = [ln.strip() for ln in str(cause).splitlines() if ln.strip()]
        msg = _parser_message(lines[-1]) if lines else "parse error"
        raise InputError(path, f"not an OpenCV FileStorage file ({msg})") from None
    if not fs.isOpened():
        raise InputError(path, "not an OpenCV FileStorage file")
    return fs


def _has(fs: cv2.FileStorage, key: str) -> bool:
    return not fs.getNode(key).empty()


def _mat(fs: cv2.FileStorage, path: Path, key: str) -> np.ndarray:
    node = fs.getNode(key)
    if node.empty():
        raise InputError(path, f'missing field "{key}"')
    m = node.mat() if node.isMap() else None
    if m is None and node.isSeq():
        m = np.array([node.at(i).real() for i in range(node.size())], np.float64)
    if m is None:
        raise InputError(path, f'field "{key}" must be an OpenCV matrix (!!opencv-matrix)')
    m = np.asarray(m, np.float64)
    if not np.isfinite(m).all():
        raise InputError(path, f'field "{key}" holds NaN or infinite values')
    return m


def _camera_matrix(fs: cv2.FileStorage, path: Path, key: str) -> np.ndarray:
    K = _mat(fs, path, key)
    if K.shape != (3, 3):
        raise InputError(path, f'field "{key}" has shape {K.shape}, expected (3, 3)')
    if K[0, 0] <= 0 or K[1, 1] <= 0 or K[2, 2] != 1 or K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0:
        raise InputError(
            path, f'field "{key}" is not a camera matrix [[fx,s,cx],[0,fy,cy],[0,0,1]] with fx, fy > 0'
        )
    return K


def _distortion(fs: cv2.FileStorage, path: Path, key: str) -> np.ndarray:
    if not _has(fs, key):
        raise InputError(path, f'missing field "{key}"')
    d = _mat(fs, path, key)
    if d.ndim != 2 or 1 not in d.shape or d.size not in _DIST_SIZES:
        raise InputError(
            path, f'field "{key}" must be 1xN distortion coefficients, N in {_DIST_SIZES}, got {d.shape}'
        )
    d = d.ravel()
    return np.append(d, 0.0) if d.size == 4 else d


def _int(fs: cv2.FileStorage, path: Path, key: str) -> int:
    node = fs.getNode(key)
    v = node.real() if node.isReal() or node.isInt() else None
    if v is None or v != int(v) or v < 1:
        raise InputError(path, f'field "{key}" must be a positive integer')
    return int(v)


def _size(fs: cv2.FileStorage, path: Path, device: int) -> tuple[int, int] | None:
    if device == 1 and _has(fs, "img_shape"):  # procam naming: [rows, cols], as numpy's shape
        vals = list(_mat(fs, path, "img_shape").ravel())
        if len(vals) != 2 or any(v != int(v) or v < 1 for v in vals):
            raise InputError(path, 'field "img_shape" must be [rows, cols] in pixels')
        return int(vals[1]), int(vals[0])
    for keys in _SIZE_KEYS[device]:
        if len(keys) == 2 and all(_has(fs, k) for k in keys):
            return _int(fs, path, keys[0]), _int(fs, path, keys[1])
        if len(keys) == 1 and _has(fs, keys[0]):
            node = fs.getNode(keys[0])
            vals = (
                [node.at(i).real() for i in range(node.size())]
                if node.isSeq()
                else list(_mat(fs, path, keys[0]).ravel())
            )
            if len(vals) != 2 or any(v != int(v) or v < 1 for v in vals):
                raise InputError(path, f'field "{keys[0]}" must be [width, height] in pixels')
            return int(vals[0]), int(vals[1])
        if len(keys) == 2 and any(_has(fs, k) for k in keys):
            missing = next(k for k in keys if not _has(fs, k))
            raise InputError(path, f'missing field "{missing}"')
    return None


def detect_naming(fs: cv2.FileStorage, path: Path) -> str:
    """``"graylight"`` or ``"stereo"``: which naming the file uses (InputError when neither)."""
    for name, keys in READ_NAMINGS.items():
        if _has(fs, keys[0]):
            return name
    raise InputError(
        path,
        'has none of "camera_matrix" (graylight naming), "K1" (stereoCalibrate naming), "cam_int" (procam)',
    )


def read_opencv_rig(
    path: str | os.PathLike[str],
    *,
    camera_size: tuple[int, int] | None = None,
    projector_size: tuple[int, int] | None = None,
    units: str | None = None,
) -> Rig:
    """Read an OpenCV stereo calibration (either naming) as a :class:`~shared.formats.rig.Rig`.

    ``camera_size``/``projector_size`` (width, height) are used when the file has no size for
    that device, and must agree with the file's when it has one. ``units`` overrides the file's
    ``units`` key (default mm).
    """
    path = Path(path)
    fs = _open(path)
    try:
        naming = detect_naming(fs, path)
        k1, d1, k2, d2 = READ_NAMINGS[naming]
        r_keys, t_keys = _RT_KEYS.get(naming, _RT_DEFAULT)
        r_key = next((k for k in r_keys if _has(fs, k)), r_keys[0])
        t_key = next((k for k in t_keys if _has(fs, k)), t_keys[0])
        K1 = _camera_matrix(fs, path, k1)
        D1 = _distortion(fs, path, d1)
        K2 = _camera_matrix(fs, path, k2)
        D2 = _distortion(fs, path, d2)
        R = _mat(fs, path, r_key)
        if R.shape == (3, 1) or R.shape == (1, 3):  # a Rodrigues vector
            R = cv2.Rodrigues(R)[0]
        if R.shape != (3, 3):
            raise InputError(
                path, f'field "{r_key}" has shape {R.shape}, expected (3, 3) or a Rodrigues vector'
            )
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise InputError(path, f'field "{r_key}" is not a rotation matrix')
        T = _mat(fs, path, t_key)
        if T.size != 3:
            raise InputError(path, f'field "{t_key}" has shape {T.shape}, expected (3, 1)')
        T = T.ravel()
        if np.linalg.norm(T) == 0:
            raise InputError(path, f'field "{t_key}" is zero: the two devices cannot share an optical centre')
        sizes = []
        for device, given, flag in (
            (1, camera_size, "--camera-size"),
            (2, projector_size, "--projector-size"),
        ):
            found = _size(fs, path, device)
            if found is not None and given is not None and tuple(given) != found:
                raise InputError(
                    flag, f"{given[0]}x{given[1]} disagrees with the file's {found[0]}x{found[1]}"
                )
            size = found or (tuple(given) if given is not None else None)
            if size is None:
                keys = " or ".join(f'"{"/".join(k)}"' for k in _SIZE_KEYS[device][:2])
                raise InputError(path, f"no image size for device {device} ({keys}): pass {flag} WxH")
            sizes.append(size)
        if units is None:
            node = fs.getNode("units")
            units = node.string() if not node.empty() and node.isString() and node.string() else "mm"
    finally:
        fs.release()
    rig = Rig(
        camera=Device(width=sizes[0][0], height=sizes[0][1], K=K1, dist=D1),
        projector=Device(width=sizes[1][0], height=sizes[1][1], K=K2, dist=D2),
        R=R,
        T=T,
        units=units,
    )
    return parse_rig(rig.to_json(), path)  # rig.json's own checks, so the result loads as one


def write_opencv_rig(rig: Rig, path: str | os.PathLike[str], naming: str = "graylight") -> Path:
    """Write ``rig`` as an OpenCV FileStorage YAML in ``naming`` (``graylight`` or ``stereo``),
    with both devices' sizes and the units; atomic."""
    if naming not in NAMINGS:
        raise InputError("naming", f"must be one of {', '.join(NAMINGS)}, got {naming!r}")
    path = Path(path)
    k1, d1, k2, d2 = NAMINGS[naming]
    suffix = path.suffix if path.suffix in (".yaml", ".yml", ".xml", ".json") else ".yaml"
    with atomic_file(path, suffix=suffix) as tmp:
        fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
        fs.write("camera_width", int(rig.camera.width))
        fs.write("camera_height", int(rig.camera.height))
        fs.write(k1, np.asarray(rig.camera.K, np.float64))
        fs.write(d1, np.asarray(rig.camera.dist, np.float64).reshape(1, -1))
        fs.write("projector_width", int(rig.projector.width))
        fs.write("projector_height", int(rig.projector.height))
        fs.write(k2, np.asarray(rig.projector.K, np.float64))
        fs.write(d2, np.asarray(rig.projector.dist, np.float64).reshape(1, -1))
        fs.write("R", np.asarray(rig.R, np.float64))
        fs.write("T", np.asarray(rig.T, np.float64).reshape(3, 1))
        fs.write("units", rig.units)
        fs.release()
    return path
