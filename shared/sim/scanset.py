"""Multi-view scan sets in the virtual rig: N captures of one object, with the true pose of every view.

``simulate_scanset("bunny", out, views=8, mode="turntable")`` writes a ``graylight-scanset-v1``
folder (:mod:`shared.formats.scanset`): ``scanset.json``, a shared ``rig.json``, captures
``view_00`` ... (each a full ``graycode-v1`` capture with its own ``truth.npz``) and the scan set's
``truth.npz``:

- ``poses`` (V, 4, 4) float64: the true pose of every view, ``X_set = R @ X_view + T`` (mm, view 0's frame);
- ``axis_direction`` (3,), ``axis_point`` (3,) mm: the turntable's (or orbit's) true axis in view 0's frame;
- ``angles_deg`` (V,): the true rotation of every view about it;
- ``mesh_vertices`` (M, 3) float64 mm and ``mesh_faces`` (F, 3) int32: the object's true surface in
  view 0's frame (the turntable plate is not part of it; ``surface`` index 0 in the views' truth
  files is the object, 1 the plate).

Each view's own ``truth.npz`` (:mod:`shared.sim.simulate`) labels every pixel (``labels``, int8,
codes of :mod:`shared.sim.scenes`): -1 nothing, 0 object, 1 plate, 2 support (the table top),
3 the turntable's base, 4 the backdrop.

Modes. ``turntable`` (what a real turntable rig sees): the object stands where the single-view
scene frames it, on a plain plate (``PLATE_THICKNESS`` mm, light grey, round: it turns with the
object by ``360 / N`` degrees per view yet looks static) on the turntable's static base
(``BASE_HEIGHT`` mm, dark, ``BASE_MARGIN`` mm wider than the plate) on a laminate table top, before
a cloth backdrop ``BACKDROP_DISTANCE`` mm behind the axis; the rig, table, base and backdrop stay
put and fill most of the image. The set carries the angles in ``"turntable"`` and, only with
``roi=True`` (``--roi``), an ``"roi"`` sphere about the axis that holds the object: a real capture
has no such crop. ``orbit``: the rig moves around the object on a circle (the object, a textured
plate and the floor turn together in the camera frame, the wall is left out because the rig
passes behind it); no angles are written, the views have to register from their overlap.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from shared.core.errors import InputError
from shared.formats.mesh import TriangleMesh
from shared.formats.rig import save_rig
from shared.formats.scanset import SCANSET_FILE, Roi, scanset_doc, write_scanset
from shared.sim.scenes import (
    LABEL_BACKDROP,
    LABEL_BASE,
    LABEL_PLATE,
    LABEL_SUPPORT,
    Material,
    MeshObject,
    Scene,
    TexturedPlane,
    build_scene,
    rotation_about,
)
from shared.sim.simulate import ImagingParams, make_rig, simulate_capture
from shared.sim.truth import truth_file

log = logging.getLogger(__name__)

__all__ = ["MODES", "ScanSetTruth", "load_scanset_truth", "simulate_scanset", "turntable_scenes"]

MODES = ("turntable", "orbit")
TRUTH_FILE = "truth.npz"
#: An orbit set's plate (the object stands on it; the whole stage turns in the camera frame), mm.
ORBIT_PLATE_HEIGHT = 25.0
#: A turntable set's plate: thickness; the static base under it: height and how far it reaches
#: beyond the plate; the backdrop's distance behind the axis (mm).
PLATE_THICKNESS = 12.0
BASE_HEIGHT = 30.0
BASE_MARGIN = 15.0
BACKDROP_DISTANCE = 400.0


class ScanSetTruth:
    """The scan set's truth arrays (see the module docstring)."""

    def __init__(self, poses: np.ndarray, axis_direction: np.ndarray, axis_point: np.ndarray,
                 angles_deg: np.ndarray, mesh_vertices: np.ndarray, mesh_faces: np.ndarray) -> None:
        self.poses = poses
        self.axis_direction = axis_direction
        self.axis_point = axis_point
        self.angles_deg = angles_deg
        self.mesh_vertices = mesh_vertices
        self.mesh_faces = mesh_faces


def load_scanset_truth(path: str | os.PathLike[str]) -> ScanSetTruth:
    """Read a scan set's ``truth.npz`` (or the folder holding it)."""
    with np.load(truth_file(path, "scan set ground-truth file")) as z:
        return ScanSetTruth(**{k: z[k] for k in ("poses", "axis_direction", "axis_point", "angles_deg",
                                                 "mesh_vertices", "mesh_faces")})


def _rigid(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    G = np.eye(4)
    G[:3, :3] = R
    G[:3, 3] = t
    return G


def _cylinder(radius: float, height: float, segments: int = 96) -> TriangleMesh:
    """A closed-top cylinder standing on y = 0 (y up), axis through the origin."""
    a = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    ring = np.stack([radius * np.cos(a), np.zeros(segments), radius * np.sin(a)], axis=1)
    top = ring + [0.0, height, 0.0]
    verts = np.concatenate([ring, top, [[0.0, height, 0.0]]])
    k = np.arange(segments)
    k1 = (k + 1) % segments
    side = np.concatenate([np.stack([k, k1, segments + k], 1), np.stack([k1, segments + k1, segments + k], 1)])
    cap = np.stack([segments + k, segments + k1, np.full(segments, 2 * segments)], 1)
    return TriangleMesh(vertices=verts, faces=np.concatenate([side, cap]).astype(np.int32))


def _move(surface, G: np.ndarray):
    """A surface moved by the rigid motion ``G`` (4x4) of the camera frame."""
    R, t = G[:3, :3], G[:3, 3]
    if isinstance(surface, MeshObject):
        return MeshObject(mesh=surface.mesh, R=R @ surface.R, t=R @ surface.t + t, scale=surface.scale,
                          material=surface.material, seed=surface.seed, label=surface.label)
    if isinstance(surface, TexturedPlane):
        return replace(surface, R=R @ surface.R, t=R @ surface.t + t)
    raise InputError("scene", f"cannot move a {type(surface).__name__} surface")


def _turntable_textures(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Albedo images of the table top (a fine-grained laminate) and the backdrop (a mottled cloth)."""
    rng = np.random.default_rng(seed)
    # Table: wood-like laminate, grain along the plate's x axis, 2 mm texels.
    grain = cv2.GaussianBlur(rng.random((750, 700)).astype(np.float32), (0, 0), sigmaX=12.0, sigmaY=0.8)
    grain = (grain - grain.min()) / max(float(np.ptp(grain)), 1e-6)
    table = np.stack([0.50 + 0.16 * grain, 0.36 + 0.12 * grain, 0.24 + 0.08 * grain], axis=-1)
    # Backdrop: grey-blue cloth with soft blotches, 4 mm texels.
    blot = cv2.GaussianBlur(rng.random((260, 360)).astype(np.float32), (0, 0), 6.0)
    blot = (blot - blot.min()) / max(float(np.ptp(blot)), 1e-6)
    weave = rng.random((260, 360)).astype(np.float32)
    cloth = (0.85 + 0.25 * blot + 0.05 * weave)[:, :, None] * np.array([0.36, 0.40, 0.46], np.float32)
    return np.clip(table, 0, 1).astype(np.float32), np.clip(cloth, 0, 1).astype(np.float32)


def _turntable_stage(obj: MeshObject, point: np.ndarray, up: np.ndarray, e1: np.ndarray, e2: np.ndarray,
                     views: int, seed: int) -> tuple[MeshObject, list]:
    """The turntable's plate (moving) and the static stage around it, in view 0's camera frame.

    ``point`` is the axis's point on the plate's top (where the object stands), ``up`` the axis,
    ``e1`` and ``e2`` the horizontal directions (world X, and world Z towards the camera). Returns the
    plate and the static surfaces: the turntable's base, the table top and the backdrop
    ``BACKDROP_DISTANCE`` mm behind the axis.
    """
    v = obj.placed.vertices
    rel = v - point
    radial = float(np.max(np.linalg.norm(rel - np.outer(rel @ up, up), axis=1)))
    plate_r = max(1.1 * radial, 80.0)
    # A facet count that is a multiple of the views: every turn maps the plate's facets onto
    # themselves, so the plate is exactly static in the images, as a round plate is.
    segments = views * int(np.ceil(192 / views))
    Ru = np.column_stack([e1, up, np.cross(e1, up)])  # cylinder frame: y = up
    plate = MeshObject(mesh=_cylinder(plate_r, PLATE_THICKNESS, segments), R=Ru, t=point - up * PLATE_THICKNESS,
                       material=Material(albedo=(0.62, 0.62, 0.60)), seed=seed + 7, label=LABEL_PLATE)
    table_level = point - up * (PLATE_THICKNESS + BASE_HEIGHT)
    base = MeshObject(mesh=_cylinder(plate_r + BASE_MARGIN, BASE_HEIGHT, segments), R=Ru, t=table_level,
                      material=Material(albedo=(0.09, 0.09, 0.10), specular=0.3, shininess=30.0), seed=seed + 8,
                      label=LABEL_BASE)
    tex_table, tex_cloth = _turntable_textures(seed + 11)
    width = 1400.0
    # Table top: from the backdrop towards the camera, x along e1, y along e2 (towards the camera).
    Rt = np.column_stack([e1, e2, np.cross(e1, e2)])
    table = TexturedPlane(Rt, table_level - e1 * width / 2 - e2 * BACKDROP_DISTANCE, tex_table, 1500.0 / 750,
                          label=LABEL_SUPPORT)
    # Backdrop: vertical, facing the camera, from below the table top (hidden behind it) upwards.
    Rb = np.column_stack([e1, -up, np.cross(e1, -up)])
    top = table_level + up * 990.0
    backdrop = TexturedPlane(Rb, top - e1 * width / 2 - e2 * BACKDROP_DISTANCE, tex_cloth, 1040.0 / 260,
                             label=LABEL_BACKDROP)
    return plate, [base, table, backdrop]


def _roi_about_axis(vertices: np.ndarray, point: np.ndarray, up: np.ndarray) -> Roi:
    """The smallest sphere centred on the axis holding every vertex, with a margin (4 % and 6 mm)
    for the decoder's noise at the silhouette."""
    h = (vertices - point) @ up
    cand = np.linspace(float(h.min()), float(h.max()), 201)
    radii = [float(np.max(np.linalg.norm(vertices - (point + up * c), axis=1))) for c in cand]
    k = int(np.argmin(radii))
    return Roi(center=point + up * cand[k], radius=1.04 * radii[k] + 6.0)


def turntable_scenes(scene: str, views: int, mode: str = "turntable", seed: int = 0
                     ) -> tuple[list[Scene], np.ndarray, np.ndarray, np.ndarray, Roi, TriangleMesh]:
    """The N scenes of a turntable or orbit scan set of a mesh scene.

    Returns the scenes (camera frame of each view; surface 0 is the object, 1 the plate), the true
    poses (V, 4, 4), the axis direction and a point on it (view 0's frame, mm), the region of
    interest and the object's placed mesh.
    """
    if mode not in MODES:
        raise InputError("mode", f"must be one of {', '.join(MODES)}, got {mode!r}")
    if views < 2:
        raise InputError("--views", f"a scan set needs at least two views, got {views}")
    base = build_scene(scene, seed=seed)
    obj = base.surfaces[0]
    floor = base.surfaces[1] if len(base.surfaces) > 1 else None
    if not isinstance(obj, MeshObject) or not isinstance(floor, TexturedPlane):
        raise InputError("--scene", f"scene {scene!r} is not a mesh on a floor; use one of bunny, teapot, spot, fandisk")
    up = -floor.R[:, 2]
    if up[1] > 0:  # world up points against the camera's Y (down) axis
        up = -up
    e1, e2 = floor.R[:, 0], floor.R[:, 1]
    v = obj.placed.vertices
    c1, c2, ch = v @ e1, v @ e2, v @ up
    foot = e1 * 0.5 * (c1.min() + c1.max()) + e2 * 0.5 * (c2.min() + c2.max())
    base_h = float(ch.min())
    point = foot + up * (base_h - float(np.dot(foot, up)))  # on the floor, under the object's centre
    angles = np.arange(views) * 360.0 / views
    if mode == "turntable":
        # The object stays where the single-view scene frames it; the plate's top is the old floor.
        placed = obj
        plate, static = _turntable_stage(obj, point, up, e1, e2, views, seed)
        roi = _roi_about_axis(v, point, up)
    else:
        placed, plate, static, roi = _orbit_stage(obj, floor, point, up, e1)
    scenes = []
    poses = []
    for a in angles:
        G = _rigid(rotation_about(up, float(a)), point - rotation_about(up, float(a)) @ point)
        moving = [_move(placed, G), _move(plate, G)]
        rest = static if mode == "turntable" else [_move(s, G) for s in static]
        scenes.append(Scene(name=f"{base.name}-{mode}-{a:.1f}", surfaces=[*moving, *rest],
                            description=f"{base.description}; {mode} view at {a:.2f} degrees"))
        poses.append(np.linalg.inv(G))
    return scenes, np.stack(poses), up, point, roi, placed.placed


def _orbit_stage(obj: MeshObject, floor: TexturedPlane, point: np.ndarray, up: np.ndarray, e1: np.ndarray
                 ) -> tuple[MeshObject, MeshObject, list, Roi]:
    """An orbit set's object raised onto a textured plate on the floor (all turn together in the
    camera frame; the wall is left out because the rig passes behind it), and its region of interest."""
    raised = MeshObject(mesh=obj.mesh, R=obj.R, t=obj.t + up * ORBIT_PLATE_HEIGHT, scale=obj.scale,
                        material=obj.material, seed=obj.seed)
    v = obj.placed.vertices
    ch = v @ up
    height = float(ch.max() - ch.min())
    centre = point + up * (ORBIT_PLATE_HEIGHT + 0.5 * height)
    radius = float(np.max(np.linalg.norm(raised.placed.vertices - centre, axis=1))) * 1.04
    foot_r = float(np.max(np.linalg.norm((v - point) - np.outer((v - point) @ up, up), axis=1)))
    reach = np.sqrt(max(radius**2 - (ORBIT_PLATE_HEIGHT + 0.5 * height) ** 2, 0.0))
    plate_r = max(1.08 * foot_r, reach + 5.0)
    Rp = np.column_stack([e1, up, np.cross(e1, up)])
    plate = MeshObject(mesh=_cylinder(plate_r, ORBIT_PLATE_HEIGHT), R=Rp, t=point, material=Material(
        albedo=(0.42, 0.40, 0.38), variation=0.35, wavelength=25.0), seed=obj.seed + 7, label=LABEL_PLATE)
    return raised, plate, [floor], Roi(center=centre, radius=radius)


def simulate_scanset(
    scene: str,
    out_dir: str | os.PathLike[str],
    *,
    views: int = 8,
    mode: str = "turntable",
    size: tuple[int, int] = (2048, 1536),
    projector: tuple[int, int] = (1024, 768),
    seed: int = 0,
    imaging: ImagingParams | None = None,
    overwrite: bool = False,
    roi: bool = False,
) -> Path:
    """Render a turntable or orbit scan set of a mesh scene into ``out_dir`` (see the module docstring).

    ``roi``: also write the scan set's ``roi`` sphere that crops every view to the object (a real
    capture has none; it is for tests and comparisons of the crop).

    Assembled under a temporary name beside ``out_dir`` and renamed when complete. Returns the
    path of ``scanset.json``.
    """
    out = Path(out_dir).absolute()
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        if not overwrite:
            raise InputError(out, "output folder exists and is not empty")
        if not (out / SCANSET_FILE).is_file():
            raise InputError(out, "output folder exists and does not hold a scan set; refusing to replace it")
    scenes, poses, up, point, sphere, mesh = turntable_scenes(scene, views, mode, seed)
    rig = make_rig(camera_size=size, projector_size=projector, seed=seed)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
    tmp.chmod(0o755)
    try:
        save_rig(rig, tmp / "rig.json")
        entries = []
        for i, sc in enumerate(scenes):
            name = f"view_{i:02d}"
            simulate_capture(sc, rig, tmp / name, seed=seed * 1000 + i, imaging=imaging)
            entries.append({"capture": name})
            log.info("scan set %s: %s rendered", out.name, name)
        angles = np.arange(views) * 360.0 / views
        np.savez(tmp / TRUTH_FILE, poses=poses, axis_direction=up, axis_point=point, angles_deg=angles,
                 mesh_vertices=mesh.vertices, mesh_faces=mesh.faces)
        doc = scanset_doc(entries, rig="rig.json", turntable_deg=list(angles) if mode == "turntable" else None,
                          roi=sphere if roi else None,
                          extra={"simulated": {"scene": scene, "mode": mode, "views": views, "seed": seed,
                                               "truth": TRUTH_FILE}})
        write_scanset(tmp, doc)
        if out.exists():
            shutil.rmtree(out) if out.is_dir() else out.unlink()
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out / SCANSET_FILE
