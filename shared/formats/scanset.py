"""The scan-set contract ``graylight-scanset-v1``: many views of one object, read from ``scanset.json``.

A scan set is a folder with ``scanset.json``::

    {"format": "graylight-scanset-v1", "rig": "rig.json",
     "views": [{"capture": "view_00"},
               {"capture": "view_01", "pose": {"R": [[1,0,0],[0,1,0],[0,0,1]], "T": [0,0,0]}},
               {"cloud": "scan_03.ply", "units": "m"}],
     "turntable": {"angles_deg": [0, 30, 60]},
     "roi": {"center": [0, 0, 1000], "radius": 200}}

- Each view is a ``graycode-v1`` capture in the named sub-folder (``"capture"``) or a point cloud
  some scanner already made (``"cloud"``: any PLY with ``x y z``, colour and normals used when
  present, in that view's sensor frame). ``"units"`` (``"mm"`` default, or ``"m"``) says what a
  cloud's numbers mean; results are in mm. ``"name"`` is optional (default: the file's stem).
- ``rig`` (shared by every captured view; a capture's own ``rig`` field overrides it) is optional.
- ``pose`` maps the view's camera frame into the scan set's frame (view 0's camera frame):
  ``X_set = R @ X_view + T`` in the view's units. It is a hint, never taken as truth.
- ``turntable.angles_deg``: one angle per view, degrees, the sign of the rotation unknown; the axis
  is not given.
- ``roi`` (optional, this implementation's extension): a sphere in every view's sensor frame,
  in mm; points outside it (background that does not turn with the object) are left out of the
  registration and the merge.

:func:`load_scanset` validates everything that can be checked without decoding pixels and
raises :class:`~shared.core.errors.InputError` with a one-line message naming the view or field.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from shared.core.errors import InputError, relative_message
from shared.core.files import read_json, write_json_atomic
from shared.core.jsonsafe import finite_number
from shared.core.paths import confine
from shared.formats.capture import CAPTURE_FILE, load_capture
from shared.formats.images import probe_image
from shared.formats.ply import read_header
from shared.formats.rig import check_rig_matches, load_rig

__all__ = [
    "FORMAT", "SCANSET_FILE", "UNITS", "Roi", "ScanSet", "ViewSpec",
    "load_scanset", "parse_scanset", "pose_json", "scanset_doc", "write_scanset",
]  # fmt: skip

FORMAT = "graylight-scanset-v1"
SCANSET_FILE = "scanset.json"
#: Millimetres per unit of each accepted ``units`` value.
UNITS = {"mm": 1.0, "m": 1000.0}
#: Most views a scan set may hold, the longest view name, and the largest coordinate (mm, or
#: the view's units) a pose, roi or angle may give: values past these are typing errors that
#: would otherwise fail late, inside the registration.
MAX_VIEWS = 1000
MAX_NAME_CHARS = 128
MAX_COORDINATE = 1e7
MAX_ANGLE_DEG = 3600.0
#: The keys of each object of the contract; any other is an error naming it and, for the
#: misplacements seen in practice, where it belongs.
_TOP_KEYS = ("format", "rig", "views", "turntable", "roi", "simulated")
_CAPTURE_VIEW_KEYS = ("capture", "name", "pose")
_CLOUD_VIEW_KEYS = ("cloud", "name", "units", "pose")
_BELONGS = {
    "units": 'goes in each cloud view ({"cloud": "scan.ply", "units": "m"}); a captured view\'s units are its rig\'s',
    "pose": "goes in a view",
    "angles_deg": 'goes in "turntable" ({"turntable": {"angles_deg": [...]}})',
    "center": 'goes in "roi"',
    "radius": 'goes in "roi"',
}
#: How far ``R @ R.T`` may be from the identity (and det(R) from 1) for a pose to count as a rotation.
ROTATION_TOLERANCE = 1e-4


@dataclass(frozen=True)
class Roi:
    """A sphere in every view's sensor frame, mm: the region that turns with the object."""

    center: np.ndarray  # (3,) float64 mm
    radius: float  # mm

    def to_json(self) -> dict[str, Any]:
        return {"center": [float(v) for v in self.center], "radius": float(self.radius)}


@dataclass(frozen=True)
class ViewSpec:
    """One view of a scan set. Paths are absolute.

    kind : ``"capture"`` or ``"cloud"``.
    path : the capture folder or the PLY file.
    units : ``"mm"`` or ``"m"``: the view's coordinates (a capture's are its rig's).
    rig : the ``rig.json`` that applies to a captured view (its own, else the scan set's).
    pose : ``(R (3, 3), T (3,))`` float64 hint, ``X_set = R @ X_view + T`` in ``units``; None if not given.
    """

    index: int
    name: str
    kind: str
    path: Path
    units: str = "mm"
    rig: Path | None = None
    pose: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def where(self) -> str:
        """How error messages name this view."""
        return f"views[{self.index}] ({self.name})"

    @property
    def scale_mm(self) -> float:
        """Millimetres per unit of this view's coordinates."""
        return UNITS[self.units]


@dataclass(frozen=True)
class ScanSet:
    """A validated ``graylight-scanset-v1`` scan set."""

    root: Path
    views: tuple[ViewSpec, ...]
    rig: Path | None = None
    turntable_deg: np.ndarray | None = None  # (V,) float64
    roi: Roi | None = None
    extra: dict[str, Any] = field(default_factory=dict, compare=False)

    def __len__(self) -> int:
        return len(self.views)

    @property
    def path(self) -> Path:
        return self.root / SCANSET_FILE


def _number_list(value: Any, n: int | None, where: str, limit: float = MAX_COORDINATE) -> np.ndarray:
    if not isinstance(value, list) or (n is not None and len(value) != n):
        want = f"a list of {n} numbers" if n is not None else "a list of numbers"
        raise InputError(where, f"must be {want}, got {_short(value)}")
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):  # OverflowError: an integer past float's range
        raise InputError(where, f"must hold numbers only, got {_short(value)}") from None
    if arr.ndim != 1 or not np.all(np.isfinite(arr)):
        raise InputError(where, f"must hold finite numbers, got {_short(value)}")
    if np.abs(arr).max(initial=0.0) > limit:
        raise InputError(where, f"must hold numbers of magnitude at most {limit:g}, got {_short(value)}")
    return arr


def _no_unknown(obj: dict[str, Any], known: tuple[str, ...], where: str) -> None:
    """:class:`InputError` naming the first key the contract does not know, and where it belongs."""
    for k in obj:
        if k not in known:
            hint = _BELONGS.get(k) if isinstance(k, str) else None
            hint = hint or f"allowed here: {', '.join(known)}"
            raise InputError(f"{where}.{k}" if where else str(k)[:60], f"unknown field: {hint}")


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _pose(value: Any, where: str) -> tuple[np.ndarray, np.ndarray]:
    if not isinstance(value, dict) or "R" not in value or "T" not in value:
        raise InputError(where, 'must be an object with "R" (3x3) and "T" (3)')
    _no_unknown(value, ("R", "T"), where)
    R_rows = value["R"]
    if not isinstance(R_rows, list) or len(R_rows) != 3:
        raise InputError(f"{where}.R", f"must be a 3x3 matrix, got {_short(R_rows)}")
    R = np.stack([_number_list(row, 3, f"{where}.R") for row in R_rows])
    T = _number_list(value["T"], 3, f"{where}.T")
    err = float(np.abs(R @ R.T - np.eye(3)).max())
    det = float(np.linalg.det(R))
    if err > ROTATION_TOLERANCE or abs(det - 1.0) > ROTATION_TOLERANCE:
        raise InputError(f"{where}.R", f"is not a rotation (|R R^T - I| = {err:.3g}, det = {det:.6g})")
    return R, T


def _resolve(root: Path, value: Any, where: str, kind: str, check: bool) -> Path:
    """``root / value`` under the one confinement rule (:func:`shared.core.paths.confine`): a path
    leading out of the scan set's folder is refused with a text that says nothing of its target."""
    return confine(root, value, where=where, folder="scan set folder", kind=kind, check=check)


def _view_name(doc: dict[str, Any], default: str, where: str) -> str:
    name = doc.get("name")
    if name is None:
        return default
    if not isinstance(name, str) or not name or len(name) > MAX_NAME_CHARS:
        raise InputError(f"{where}.name", f"must be a string of 1..{MAX_NAME_CHARS} characters, got {_short(name)}")
    return name


def _capture_view(root: Path, i: int, doc: dict[str, Any], set_rig: Path | None, check: bool) -> ViewSpec:
    if "units" in doc:
        raise InputError(f"views[{i}].units", "applies to cloud views only (a capture's units are its rig's)")
    _no_unknown(doc, _CAPTURE_VIEW_KEYS, f"views[{i}]")
    path = _resolve(root, doc["capture"], f"views[{i}].capture", "dir", check)
    name = _view_name(doc, path.name, f"views[{i}]")
    where = f"views[{i}] ({name})"
    if not check:
        return ViewSpec(index=i, name=name, kind="capture", path=path, rig=set_rig)
    if not (path / CAPTURE_FILE).is_file():
        raise InputError(where, f"capture not found: {doc['capture']}/{CAPTURE_FILE} does not exist")
    try:
        capture = load_capture(path, check=check)
    except InputError as exc:
        raise InputError(where, f"bad capture: {relative_message(exc, root)}") from None
    rig = capture.rig or set_rig
    units = "mm"
    if rig is not None:
        try:
            units = load_rig(rig).units
        except InputError as exc:
            raise InputError(where, f"bad rig: {relative_message(exc, root)}") from None
        if units not in UNITS:
            raise InputError(where, f"rig units {units!r} are not one of {', '.join(UNITS)}")
    return ViewSpec(index=i, name=name, kind="capture", path=path, units=units, rig=rig)


def _cloud_view(root: Path, i: int, doc: dict[str, Any], check: bool) -> ViewSpec:
    _no_unknown(doc, _CLOUD_VIEW_KEYS, f"views[{i}]")
    path = _resolve(root, doc["cloud"], f"views[{i}].cloud", "file", check)
    name = _view_name(doc, path.stem, f"views[{i}]")
    where = f"views[{i}] ({name})"
    units = doc.get("units", "mm")
    if not isinstance(units, str) or units not in UNITS:
        raise InputError(f"{where}.units", f"must be one of {', '.join(UNITS)}, got {_short(units)}")
    if check:
        try:
            header = read_header(path)
        except InputError as exc:
            raise InputError(where, f"bad point cloud: {relative_message(exc, root)}") from None
        if header.count < 3:
            raise InputError(where, f"point cloud {doc['cloud']} holds {header.count} points")
    return ViewSpec(index=i, name=name, kind="cloud", path=path, units=units)


def _check_capture_sizes(root: Path, views: list[ViewSpec], set_rig: Path | None) -> None:
    """A captured view without a rig of its own must have the image size of the others (and of the rig)."""
    first: tuple[ViewSpec, tuple[int, int]] | None = None
    for v in views:
        if v.kind != "capture":
            continue
        capture = load_capture(v.path, check=False)
        try:
            info = probe_image(capture.white)
        except InputError as exc:
            raise InputError(v.where, f"bad capture: {relative_message(exc, root)}") from None
        size = (info.width, info.height)
        if v.rig is None:
            raise InputError(v.where, 'no rig: the capture names none and scanset.json has no "rig" field')
        own = capture.rig is not None
        if first is not None and not own and first[1] != size:
            other, osize = first
            raise InputError(
                v.where,
                f"images are {size[0]}x{size[1]} but {other.where} are {osize[0]}x{osize[1]}; views of "
                "different sizes need their own rig in capture.json",
            )
        if first is None:
            first = (v, size)
        try:
            check_rig_matches(load_rig(v.rig), size, (capture.projector_width, capture.projector_height), v.rig)
        except InputError as exc:
            raise InputError(v.where, f"rig does not fit: {relative_message(exc, root)}") from None


def parse_scanset(doc: Any, root: Path, check: bool = True) -> ScanSet:
    """Validate a parsed ``scanset.json`` document whose paths are relative to ``root``."""
    where = root / SCANSET_FILE
    if not isinstance(doc, dict):
        raise InputError(where, "must hold a JSON object")
    if doc.get("format") != FORMAT:
        raise InputError(f"{where}: format", f"must be {FORMAT!r}, got {_short(doc.get('format'))}")
    _no_unknown(doc, _TOP_KEYS, "")
    if doc.get("simulated") is not None and not isinstance(doc["simulated"], dict):
        raise InputError("simulated", "must be an object (what graylight simulate wrote)")
    set_rig = None
    if doc.get("rig") is not None:
        set_rig = _resolve(root, doc["rig"], "rig", "file", check)
    views_doc = doc.get("views")
    if not isinstance(views_doc, list):
        raise InputError("views", "missing or not a list")
    if not 2 <= len(views_doc) <= MAX_VIEWS:
        raise InputError("views", f"a scan set needs 2..{MAX_VIEWS} views, got {len(views_doc)}")
    views: list[ViewSpec] = []
    for i, vd in enumerate(views_doc):
        if not isinstance(vd, dict):
            raise InputError(f"views[{i}]", "must be an object")
        kinds = [k for k in ("capture", "cloud") if k in vd]
        if len(kinds) != 1:
            raise InputError(f"views[{i}]", 'must name exactly one of "capture" (a folder) or "cloud" (a PLY file)')
        view = _capture_view(root, i, vd, set_rig, check) if kinds[0] == "capture" else _cloud_view(root, i, vd, check)
        if vd.get("pose") is not None:
            view = ViewSpec(**{**view.__dict__, "pose": _pose(vd["pose"], f"{view.where}.pose")})
        views.append(view)
    names = [v.name for v in views]
    for i, n in enumerate(names):
        if n in names[:i]:
            raise InputError(views[i].where, f"view name {n!r} is used twice (set a \"name\")")
    if check:
        _check_capture_sizes(root, views, set_rig)
    angles = None
    if doc.get("turntable") is not None:
        tt = doc["turntable"]
        if not isinstance(tt, dict) or "angles_deg" not in tt:
            raise InputError("turntable", 'must be an object with "angles_deg"')
        _no_unknown(tt, ("angles_deg",), "turntable")
        a = tt["angles_deg"]
        if not isinstance(a, list) or len(a) != len(views):
            got = len(a) if isinstance(a, list) else _short(a)
            raise InputError("turntable.angles_deg", f"must give one angle per view ({len(views)}), got {got}")
        angles = _number_list(a, len(views), "turntable.angles_deg", MAX_ANGLE_DEG)
    roi = None
    if doc.get("roi") is not None:
        r = doc["roi"]
        if not isinstance(r, dict) or "center" not in r or "radius" not in r:
            raise InputError("roi", 'must be an object with "center" (3 numbers, mm) and "radius" (mm)')
        _no_unknown(r, ("center", "radius"), "roi")
        centre = _number_list(r["center"], 3, "roi.center")
        radius = r["radius"]
        if not finite_number(radius) or not 0 < radius <= MAX_COORDINATE:
            raise InputError("roi.radius", f"must be a positive number of mm up to {MAX_COORDINATE:g}, got {_short(radius)}")
        roi = Roi(center=centre, radius=float(radius))
    extra = {"simulated": doc["simulated"]} if doc.get("simulated") is not None else {}
    return ScanSet(root=root, views=tuple(views), rig=set_rig, turntable_deg=angles, roi=roi, extra=extra)


def load_scanset(path: str | os.PathLike[str], check: bool = True) -> ScanSet:
    """Read and validate a scan set (its folder or its ``scanset.json``).

    With ``check`` every view is opened far enough to know it is usable: a capture's
    ``capture.json`` and its images' headers, a cloud's PLY header; captured views that share a
    rig must share its image sizes. Pixels are not decoded.
    """
    p = Path(path).absolute()
    if p.is_dir():
        p = p / SCANSET_FILE
    doc = read_json(p, "scan set description not found (expected scanset.json)")
    return parse_scanset(doc, p.parent, check=check)


def scanset_doc(
    views: list[dict[str, Any]],
    rig: str | None = None,
    turntable_deg: list[float] | None = None,
    roi: Roi | None = None,
    extra: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """A ``scanset.json`` document; ``views`` are the per-view objects as in the contract."""
    doc: dict[str, Any] = {"format": FORMAT}
    if rig is not None:
        doc["rig"] = rig
    doc["views"] = views
    if turntable_deg is not None:
        doc["turntable"] = {"angles_deg": [float(a) for a in turntable_deg]}
    if roi is not None:
        doc["roi"] = roi.to_json()
    doc.update(extra or {})
    return doc


def write_scanset(root: str | os.PathLike[str], doc: dict[str, Any]) -> Path:
    """Write ``root/scanset.json`` atomically after validating ``doc`` (files are not checked)."""
    root = Path(root).absolute()
    parse_scanset(doc, root, check=False)
    return write_json_atomic(root / SCANSET_FILE, doc)


def pose_json(R: np.ndarray, T: np.ndarray) -> dict[str, Any]:
    """A pose as the contract writes it."""
    return {"R": np.asarray(R, float).tolist(), "T": np.asarray(T, float).ravel().tolist()}
