"""Scenes of the virtual rig: surfaces, materials and the named test scenes.

Everything is in the camera frame of the rig, in mm (OpenCV axes: X right, Y down, Z forward,
camera at the origin). A :class:`Scene` is a list of surfaces:

- :class:`TexturedPlane` — a flat rectangle at pose ``(R, t)`` carrying an albedo image printed
  at ``mm_per_texel`` (walls, floors, calibration boards: see :meth:`TexturedPlane.chessboard`);
- :class:`Sphere` — analytic sphere with a smooth procedural albedo;
- :class:`MeshObject` — a triangle mesh (e.g. from an OBJ file) placed in the camera frame.

Each surface has a :class:`Material`: RGB albedo (0..1), optional procedural variation, a
Phong specular lobe, and whether it takes part in one-bounce inter-reflection; and a ``label``,
what the surface is in a scan (the per-pixel ``labels`` of the truth, int8):

- ``LABEL_NONE`` -1: no surface (the ray leaves the scene);
- ``LABEL_OBJECT`` 0: the object scanned (meshes, spheres, the plane poster, the corner's walls);
- ``LABEL_PLATE`` 1: the turntable's plate, which turns with the object (plain: it looks static);
- ``LABEL_SUPPORT`` 2: the table top or floor the object or the turntable stands on (static);
- ``LABEL_BASE`` 3: the turntable's base under the plate (static);
- ``LABEL_BACKDROP`` 4: the wall or cloth behind (static).

Named scenes (``SCENES``, built by :func:`build_scene`): ``plane``, ``spheres``, ``corner``,
``bunny``, ``teapot``, ``spot``, ``fandisk``. Mesh scenes read ``meshes/*.obj`` under
:func:`shared.core.datapaths.shared_data_dir`; a missing file is an :class:`InputError` naming it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from shared.core.datapaths import shared_data_dir
from shared.core.errors import InputError
from shared.formats.mesh import TriangleMesh, load_obj
from shared.sim.raycast import texture_filtered

LABEL_NONE = -1
LABEL_OBJECT = 0
LABEL_PLATE = 1
LABEL_SUPPORT = 2
LABEL_BASE = 3
LABEL_BACKDROP = 4
#: Label code -> name, as documented in the module docstring.
LABELS: dict[int, str] = {LABEL_NONE: "none", LABEL_OBJECT: "object", LABEL_PLATE: "plate",
                          LABEL_SUPPORT: "support", LABEL_BASE: "base", LABEL_BACKDROP: "backdrop"}


@dataclass(frozen=True)
class Material:
    """Reflectance of a surface.

    ``albedo`` is the diffuse RGB reflectance (0..1). ``variation`` (0..1) modulates it with a
    smooth procedural pattern of period ``wavelength`` mm (spheres and meshes; planes use their
    texture). ``pattern`` (0..1) paints a solid colour texture over that (spheres and meshes):
    patches about ``pattern_size`` mm across with sharp, wavy borders, each scaling the three
    channels by its own factors in ``1 +- pattern`` (a known per-channel albedo with detail that a
    blurred or view-mixed colour estimate cannot reproduce). ``specular`` is the Phong coefficient relative to the diffuse scale (values above
    ~1 saturate the sensor in the highlight) with exponent ``shininess``. ``subsurface`` (mm) is the
    spread of light under a translucent surface (wax, skin, marble): it blurs the projected pattern
    on that surface by a Gaussian of that standard deviation. ``interreflect`` lets a
    :class:`TexturedPlane` send and receive one bounce of diffuse inter-reflection.
    """

    albedo: tuple[float, float, float] = (0.7, 0.7, 0.7)
    variation: float = 0.0
    wavelength: float = 40.0
    pattern: float = 0.0
    pattern_size: float = 8.0
    specular: float = 0.0
    shininess: float = 40.0
    subsurface: float = 0.0
    interreflect: bool = False


def _procedural(points_obj: np.ndarray, wavelength: float, seed: int) -> np.ndarray:
    """Smooth pseudo-random field in [-1, 1] over object-frame points (N, 3): a sum of plane waves."""
    rng = np.random.default_rng(seed)
    acc = np.zeros(points_obj.shape[0], np.float64)
    for _ in range(5):
        k = rng.normal(size=3)
        k *= 2 * np.pi / (wavelength * rng.uniform(0.6, 1.6) * np.linalg.norm(k))
        acc += np.sin(points_obj @ k + rng.uniform(0, 2 * np.pi))
    return np.clip(acc / 2.2, -1.0, 1.0)


def _mix64(h: np.ndarray) -> np.ndarray:
    """splitmix64's finaliser: well-spread 64-bit hashes of uint64 keys."""
    h = (h ^ (h >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    h = (h ^ (h >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return h ^ (h >> np.uint64(31))


def _colour_patches(points_obj: np.ndarray, size: float, strength: float, seed: int) -> np.ndarray:
    """Per-channel albedo factors (N, 3) float32 in ``1 +- strength``: a solid texture of patches.

    Space (object frame, mm) is cut into cubic cells of ``size`` mm on a rotated grid whose
    coordinates are first warped by a smooth field (so the borders on a surface are wavy, not
    straight); every cell draws a shared and three per-channel uniforms from a hash of its index.
    """
    rng = np.random.default_rng(seed + 0x5EED)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    p = points_obj @ q
    warp = np.stack([_procedural(points_obj, 2.5 * size, seed + 31 * k) for k in range(3)], axis=1)
    cell = np.floor((p + 0.3 * size * warp) / size).astype(np.int64)
    key = (cell[:, 0] * 73856093) ^ (cell[:, 1] * 19349663) ^ (cell[:, 2] * 83492791) ^ (seed * 2654435761)
    h = _mix64(key.astype(np.uint64))
    u = np.stack([((h >> np.uint64(16 * k)) & np.uint64(0xFFFF)).astype(np.float32) / 65535.0 for k in range(4)],
                 axis=1)
    mix = 0.5 * u[:, :1] + 0.5 * u[:, 1:]  # a shared lightness and a hue of its own per patch
    return (1.0 + strength * (2.0 * mix - 1.0)).astype(np.float32)


def _material_albedo(material: Material, points_obj: np.ndarray, seed: int) -> np.ndarray:
    base = np.asarray(material.albedo, np.float32)[None, :]
    out = np.repeat(base, points_obj.shape[0], axis=0)
    if material.variation > 0:
        f = _procedural(points_obj, material.wavelength, seed).astype(np.float32)
        out = out * (1.0 + material.variation * f)[:, None]
    if material.pattern > 0:
        out = out * _colour_patches(points_obj, material.pattern_size, material.pattern, seed)
    return out


def rotation_from_axes(x_axis: np.ndarray, y_hint: np.ndarray) -> np.ndarray:
    """Rotation whose columns are an orthonormal frame with first axis ``x_axis`` and second near ``y_hint``."""
    x = np.asarray(x_axis, float)
    x = x / np.linalg.norm(x)
    y = np.asarray(y_hint, float) - x * float(np.dot(x, y_hint))
    y = y / np.linalg.norm(y)
    return np.column_stack([x, y, np.cross(x, y)])


def rotation_about(axis: np.ndarray, angle_deg: float) -> np.ndarray:
    """Rotation matrix about ``axis`` by ``angle_deg`` (Rodrigues)."""
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    th = np.deg2rad(angle_deg)
    Kx = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(th) * Kx + (1 - np.cos(th)) * Kx @ Kx


@dataclass
class TexturedPlane:
    """A printed flat rectangle: albedo image ``texture`` at pose ``(R, t)`` in the camera frame.

    Plane coordinates ``(x, y)`` in mm map to the camera frame as ``R @ [x, y, 0] + t``: ``t`` is
    the texture's top-left corner, ``R[:, 0]`` runs along texture columns, ``R[:, 1]`` down its
    rows, ``R[:, 2]`` is the normal. Texel ``(r, c)`` covers ``x in [c, c+1) * mm_per_texel``,
    ``y in [r, r+1) * mm_per_texel``; the surface ends at the texture's edge.

    Parameters
    ----------
    R : (3, 3) rotation, plane axes as columns
    t : (3,) mm
    texture : (h, w) or (h, w, 3) RGB, uint8 (0..255) or float (0..1) albedo
    mm_per_texel : texel size in mm
    material : specular / inter-reflection settings; its ``albedo`` multiplies the texture
    """

    R: np.ndarray
    t: np.ndarray
    texture: np.ndarray
    mm_per_texel: float
    material: Material = field(default_factory=lambda: Material(albedo=(1.0, 1.0, 1.0)))
    #: Set by :meth:`chessboard`: inner corners (along width, height), square size (mm) and the
    #: plane coordinate (mm, both axes) of the printed squares' outer corner.
    board_inner_corners: tuple[int, int] | None = None
    board_square: float = 0.0
    board_origin: float = 0.0
    label: int = LABEL_OBJECT

    def __post_init__(self) -> None:
        self.R = np.asarray(self.R, np.float64)
        self.t = np.asarray(self.t, np.float64).ravel()
        tex = np.asarray(self.texture)
        tex = tex.astype(np.float32) / 255.0 if tex.dtype == np.uint8 else tex.astype(np.float32)
        if tex.ndim == 2:
            tex = np.repeat(tex[:, :, None], 3, axis=2)
        if tex.ndim != 3 or tex.shape[2] != 3:
            raise ValueError(f"texture must be (h, w) or (h, w, 3), got {tex.shape}")
        self._tex = np.ascontiguousarray(tex * np.asarray(self.material.albedo, np.float32))
        self._pyramid: list[np.ndarray] = [self._tex]

    @property
    def normal(self) -> np.ndarray:
        """(3,) unit normal ``R[:, 2]``."""
        return self.R[:, 2]

    @property
    def size_mm(self) -> tuple[float, float]:
        """(width, height) of the printed area in mm."""
        h, w = self._tex.shape[:2]
        return w * self.mm_per_texel, h * self.mm_per_texel

    def to_camera(self, xy: np.ndarray) -> np.ndarray:
        """Camera-frame points (N, 3) of plane coordinates ``xy`` (N, 2) mm."""
        xy = np.asarray(xy, float)
        return xy[:, :1] * self.R[:, 0] + xy[:, 1:2] * self.R[:, 1] + self.t

    def plane_coords(self, points: np.ndarray) -> np.ndarray:
        """Plane coordinates (N, 2) mm of camera-frame points (N, 3) (projected onto the plane)."""
        d = np.asarray(points, float) - self.t
        return np.stack([d @ self.R[:, 0], d @ self.R[:, 1]], axis=-1)

    def ray_coords(self, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ray parameter ``t`` (N,) (inf on a miss) and plane coordinates (N, 2) of rays ``origin + t * dirs``."""
        n = self.normal
        den = dirs @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (float(np.dot(self.t - origin, n))) / den
        p = origin + t[:, None] * dirs
        xy = self.plane_coords(p)
        w, h = self.size_mm
        inside = (t > 0) & (xy[:, 0] >= 0) & (xy[:, 0] < w) & (xy[:, 1] >= 0) & (xy[:, 1] < h) & np.isfinite(t)
        return np.where(inside, t, np.inf), xy

    def intersect(self, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Ray parameter (N,) of rays ``origin + t * dirs`` (N, 3) hitting the printed area; inf on a miss."""
        return self.ray_coords(origin, dirs)[0]

    def normals_at(self, points: np.ndarray) -> np.ndarray:
        return np.broadcast_to(self.normal, points.shape).copy()

    def _level(self, level: int) -> np.ndarray:
        """Mip level ``level`` of the texture (each halves the previous by area averaging)."""
        import cv2

        while len(self._pyramid) <= level:
            prev = self._pyramid[-1]
            self._pyramid.append(
                cv2.resize(prev, (max(1, prev.shape[1] // 2), max(1, prev.shape[0] // 2)), interpolation=cv2.INTER_AREA)
            )
        return self._pyramid[level]

    def albedo_at_coords(self, xy: np.ndarray, footprint_mm: np.ndarray) -> np.ndarray:
        """Area-filtered albedo (N, 3) float32 at plane coordinates ``xy`` (N, 2) mm.

        ``footprint_mm`` (N, 2): standard deviation of each sample's footprint along the plane's x
        and y axes, in mm (a camera pixel seen on the plane; pixel integration). Footprints much
        larger than a texel use a downsampled copy of the texture (mip level), so the cost per
        sample stays bounded.
        """

        fp = np.asarray(footprint_mm, np.float64) / self.mm_per_texel
        h0, w0 = self._tex.shape[:2]
        max_level = int(np.floor(np.log2(max(min(h0, w0), 1))))
        levels = np.clip(np.ceil(np.log2(np.maximum(fp.max(axis=1), 1e-9) / 1.5)), 0, max_level).astype(int)
        out = np.empty((len(xy), 3), np.float32)
        for level in np.unique(levels):
            sel = np.flatnonzero(levels == level)
            tex = self._level(int(level))
            sx, sy = tex.shape[1] / w0, tex.shape[0] / h0
            x = xy[sel, 0] / self.mm_per_texel * sx
            y = xy[sel, 1] / self.mm_per_texel * sy
            out[sel] = texture_filtered(tex, x, y, np.maximum(fp[sel, 0] * sx, 0.02), np.maximum(fp[sel, 1] * sy, 0.02))
        return out

    @classmethod
    def chessboard(
        cls,
        R: np.ndarray,
        t: np.ndarray,
        inner_corners: tuple[int, int] = (9, 7),
        square_size: float = 30.0,
        border: float = 0.5,
        texels_per_square: int = 16,
        dark: float = 0.06,
        light: float = 0.85,
        material: Material | None = None,
    ) -> TexturedPlane:
        """A printed chessboard: ``inner_corners`` = (along width, along height), like OpenCV.

        The board has ``inner_corners + 1`` squares of ``square_size`` mm, the top-left one dark,
        surrounded by a light margin of ``border`` squares. Its inner corners in plane
        coordinates are :meth:`chessboard_corners`.
        """
        nx, ny = inner_corners[0] + 1, inner_corners[1] + 1
        bt = int(round(border * texels_per_square))
        idx_x = np.arange(nx * texels_per_square) // texels_per_square
        idx_y = np.arange(ny * texels_per_square) // texels_per_square
        squares = ((idx_x[None, :] + idx_y[:, None]) % 2 == 0)
        img = np.full((ny * texels_per_square + 2 * bt, nx * texels_per_square + 2 * bt), light, np.float32)
        img[bt : bt + ny * texels_per_square, bt : bt + nx * texels_per_square] = np.where(squares, dark, light)
        return cls(R=R, t=t, texture=img, mm_per_texel=square_size / texels_per_square,
                   material=material or Material(albedo=(1.0, 1.0, 1.0)),
                   board_inner_corners=(int(inner_corners[0]), int(inner_corners[1])),
                   board_square=float(square_size), board_origin=bt * square_size / texels_per_square)

    def chessboard_corners(self) -> np.ndarray:
        """Inner corners of a :meth:`chessboard` plane: (N, 2) plane coordinates in mm, OpenCV order
        (row by row along the board's width, N = w * h)."""
        if self.board_inner_corners is None:
            raise ValueError("this plane is not a chessboard (make it with TexturedPlane.chessboard)")
        w, h = self.board_inner_corners
        sq = self.board_square
        o = self.board_origin
        gx, gy = np.meshgrid(np.arange(1, w + 1) * sq + o, np.arange(1, h + 1) * sq + o)
        return np.stack([gx.ravel(), gy.ravel()], axis=-1)

    def chessboard_object_points(self) -> np.ndarray:
        """Inner corners as (N, 3) float32 board-frame points (z = 0) with square units, first corner at origin."""
        c = self.chessboard_corners() - self.chessboard_corners()[0]
        return np.column_stack([c, np.zeros(len(c))]).astype(np.float32)


@dataclass
class Sphere:
    """An analytic sphere (centre (3,) mm, radius mm)."""

    center: np.ndarray
    radius: float
    material: Material = field(default_factory=Material)
    seed: int = 0
    label: int = LABEL_OBJECT

    def __post_init__(self) -> None:
        self.center = np.asarray(self.center, np.float64).ravel()

    def intersect(self, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        oc = origin - self.center
        a = np.einsum("ij,ij->i", dirs, dirs)
        b = dirs @ oc
        c = float(oc @ oc) - self.radius**2
        disc = b * b - a * c
        with np.errstate(invalid="ignore"):
            sq = np.sqrt(disc)
            t0 = (-b - sq) / a
            t1 = (-b + sq) / a
        t = np.where(t0 > 1e-6, t0, np.where(t1 > 1e-6, t1, np.inf))
        return np.where(disc >= 0, t, np.inf)

    def normals_at(self, points: np.ndarray) -> np.ndarray:
        return (points - self.center) / self.radius

    def albedo_at(self, points: np.ndarray) -> np.ndarray:
        return _material_albedo(self.material, points - self.center, self.seed)


@dataclass
class MeshObject:
    """A triangle mesh placed in the camera frame: vertex ``v`` goes to ``R @ (scale * v) + t``."""

    mesh: TriangleMesh
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))
    scale: float = 1.0
    material: Material = field(default_factory=Material)
    seed: int = 0
    label: int = LABEL_OBJECT

    def __post_init__(self) -> None:
        self.R = np.asarray(self.R, np.float64)
        self.t = np.asarray(self.t, np.float64).ravel()
        self.placed = self.mesh.transformed(self.R, self.t, self.scale)
        self.face_normals = self.placed.face_normals()

    def albedo_at(self, points: np.ndarray) -> np.ndarray:
        obj = (points - self.t) @ self.R
        return _material_albedo(self.material, obj, self.seed)


Surface = TexturedPlane | Sphere | MeshObject


@dataclass
class Scene:
    """A named list of surfaces in the camera frame (mm)."""

    name: str
    surfaces: list[Surface]
    description: str = ""


# ---------------------------------------------------------------------------------------------
# Named scenes. A scene lives in a "world" with Y up and the floor at y = 0, seen by the camera
# from ``eye``; :func:`_world_to_camera` moves it into the camera frame.


def _world_to_camera(eye: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) with X_cam = R @ X_world + t for a camera at ``eye`` looking at ``target`` (world Y up)."""
    z = np.asarray(target, float) - np.asarray(eye, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 1.0, 0.0])  # camera X (right) when world Y is up and camera Y points down
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ np.asarray(eye, float)


def _random_texture(rng: np.random.Generator, shape: tuple[int, int], dark: float = 0.05) -> np.ndarray:
    """A printed-poster albedo: tiles of random colours and greys, some very dark, plus smooth blotches."""
    import cv2

    h, w = shape
    tiles = rng.uniform(0.25, 0.9, size=(max(2, h // 8), max(2, w // 8), 3)).astype(np.float32)
    grey = rng.random(tiles.shape[:2]) < 0.4
    tiles[grey] = tiles[grey].mean(axis=1, keepdims=True)
    darkmask = rng.random(tiles.shape[:2]) < 0.12
    tiles[darkmask] = dark
    img = cv2.resize(tiles, (w, h), interpolation=cv2.INTER_NEAREST)
    blot = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), max(h, w) / 40)
    blot = (blot - blot.min()) / max(float(np.ptp(blot)), 1e-6)
    return np.clip(img * (0.6 + 0.4 * blot[:, :, None]), 0.0, 1.0)


def _floor_and_wall(
    Rwc: np.ndarray, twc: np.ndarray, rng: np.random.Generator, wall_z: float = -250.0, size: float = 1400.0
) -> list[Surface]:
    """A tiled floor (y = 0) and a printed back wall (z = wall_z), world frame -> camera frame."""
    tex_floor = _random_texture(rng, (96, 96))
    tex_floor = 0.55 * tex_floor + 0.2
    # Floor: plane x-axis = world +X, y-axis = world +Z (towards the camera), normal = -Y... the
    # normal's sign does not matter for intersection; shading orients it towards the viewer.
    Rf_world = np.column_stack([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])
    floor_origin = np.array([-size / 2, 0.0, wall_z])
    Rw_world = np.column_stack([[1.0, 0, 0], [0, -1.0, 0], [0, 0, 1.0]])
    wall_origin = np.array([-size / 2, size * 0.6, wall_z])
    tex_wall = _random_texture(rng, (120, 160))
    return [
        TexturedPlane(Rwc @ Rf_world, Rwc @ floor_origin + twc, tex_floor, size / 96, label=LABEL_SUPPORT),
        TexturedPlane(Rwc @ Rw_world, Rwc @ wall_origin + twc, tex_wall, size / 160, label=LABEL_BACKDROP),
    ]


def mesh_path(name: str) -> Path:
    """Path of a mesh in the shared data folder (``meshes/<name>.obj``)."""
    return shared_data_dir() / "meshes" / f"{name}.obj"


def _mesh_scene(
    name: str, file: str, height_mm: float, up_axis: int, material: Material, seed: int, yaw_deg: float = 20.0
) -> Scene:
    path = mesh_path(file)
    if not path.is_file():
        raise InputError(path, f"mesh file for scene {name!r} not found")
    mesh = load_obj(path)
    lo, hi = mesh.bounds
    scale = height_mm / float(hi[up_axis] - lo[up_axis])
    # Mesh frame -> world (Y up): bring the mesh's up axis to world Y, then yaw.
    if up_axis == 1:
        R_up = np.eye(3)
    elif up_axis == 2:
        R_up = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])
    else:
        R_up = np.array([[0, 1.0, 0], [-1.0, 0, 0], [0, 0, 1.0]])
    R_mw = rotation_about([0, 1, 0], yaw_deg) @ R_up
    v_world = (scale * mesh.vertices) @ R_mw.T
    lo_w, hi_w = v_world.min(axis=0), v_world.max(axis=0)
    centre = np.array([(lo_w[0] + hi_w[0]) / 2, -lo_w[1], (lo_w[2] + hi_w[2]) / 2])
    t_mw = np.array([-centre[0], centre[1], -centre[2]])
    rng = np.random.default_rng(seed)
    eye = np.array([0.0, 420.0, 930.0])
    target = np.array([0.0, height_mm * 0.42, 0.0])
    Rwc, twc = _world_to_camera(eye, target)
    obj = MeshObject(mesh=mesh, R=Rwc @ R_mw, t=Rwc @ t_mw + twc, scale=scale, material=material, seed=seed)
    return Scene(name=name, surfaces=[obj, *_floor_and_wall(Rwc, twc, rng)],
                 description=f"{file}.obj ({len(mesh.faces)} triangles) on a floor before a printed wall")


def scene_bunny(seed: int = 0) -> Scene:
    """Stanford bunny (~230 mm tall, marbled albedo with colour patches) on a tiled floor before a printed wall:
    projector shadows."""
    return _mesh_scene("bunny", "stanford-bunny", 230.0, 1,
                       Material(albedo=(0.72, 0.64, 0.52), variation=0.35, wavelength=35.0, pattern=0.4,
                                pattern_size=9.0), seed)


def scene_teapot(seed: int = 0) -> Scene:
    """Glossy Utah teapot: saturating Phong highlights."""
    return _mesh_scene("teapot", "teapot", 180.0, 1,
                       Material(albedo=(0.55, 0.22, 0.17), variation=0.1, pattern=0.35, pattern_size=7.0,
                                specular=2.5, shininess=60.0), seed, yaw_deg=-30)


def scene_spot(seed: int = 0) -> Scene:
    """Keenan Crane's Spot cow, in translucent wax: subsurface scattering blurs the finest stripes."""
    return _mesh_scene("spot", "spot", 220.0, 1,
                       Material(albedo=(0.8, 0.75, 0.7), variation=0.5, wavelength=50.0, pattern=0.35,
                                pattern_size=12.0, subsurface=0.5), seed,
                       yaw_deg=150)


def scene_fandisk(seed: int = 0) -> Scene:
    """Hoppe's fandisk: sharp creases."""
    return _mesh_scene("fandisk", "fandisk", 200.0, 1,
                       Material(albedo=(0.6, 0.62, 0.65), variation=0.2, pattern=0.4, pattern_size=10.0), seed,
                       yaw_deg=30)


def scene_plane(seed: int = 0) -> Scene:
    """One printed poster, tilted 25 degrees, filling the view at ~1 m: dark and coloured patches."""
    rng = np.random.default_rng(seed)
    R = rotation_about([0, 1, 0], 25.0) @ rotation_about([1, 0, 0], -10.0)
    w, h = 900.0, 700.0
    t = np.array([0.0, 0.0, 1000.0]) - R @ np.array([w / 2, h / 2, 0.0])
    tex = _random_texture(rng, (140, 180), dark=0.04)
    return Scene("plane", [TexturedPlane(R, t, tex, w / 180)], "tilted printed poster at 1 m")


def scene_spheres(seed: int = 0) -> Scene:
    """Printed wall and floor with four spheres: dark, coloured, marbled and glossy; sphere shadows on the wall."""
    rng = np.random.default_rng(seed)
    eye = np.array([0.0, 300.0, 950.0])
    Rwc, twc = _world_to_camera(eye, np.array([0.0, 90.0, 0.0]))
    surfaces: list[Surface] = list(_floor_and_wall(Rwc, twc, rng, wall_z=-200.0))
    specs = [
        ((-120.0, 60.0, 40.0), 60.0, Material(albedo=(0.08, 0.08, 0.09))),
        ((40.0, 75.0, -60.0), 75.0, Material(albedo=(0.85, 0.35, 0.2), variation=0.3, wavelength=30.0)),
        ((150.0, 50.0, 80.0), 50.0, Material(albedo=(0.5, 0.6, 0.8), specular=3.0, shininess=80.0)),
        ((-20.0, 35.0, 150.0), 35.0, Material(albedo=(0.9, 0.9, 0.85), variation=0.5, wavelength=15.0)),
    ]
    for i, (c, r, m) in enumerate(specs):
        surfaces.append(Sphere(Rwc @ np.asarray(c) + twc, r, m, seed=seed + i))
    return Scene("spheres", surfaces, "four spheres (dark, coloured, glossy, marbled) on a printed floor before a wall")


def scene_corner(seed: int = 0) -> Scene:
    """Concave corner of two light walls at 90 degrees (one-bounce inter-reflection) with a glossy sphere."""
    rng = np.random.default_rng(seed)
    apex = np.array([0.0, 0.0, 1150.0])
    h = 800.0
    wall_len = 700.0
    surfaces: list[Surface] = []
    for side in (-1.0, 1.0):
        # Each wall runs from the crease towards the camera at 45 degrees.
        along = np.array([side * np.sqrt(0.5), 0.0, -np.sqrt(0.5)])
        down = np.array([0.0, 1.0, 0.0])
        tex = 0.75 + 0.15 * _random_texture(rng, (64, 56))
        if side < 0:
            R = rotation_from_axes(-along, down)
            t = apex + along * wall_len - down * h / 2
        else:
            R = rotation_from_axes(along, down)
            t = apex - down * h / 2
        surfaces.append(TexturedPlane(R, t, tex, wall_len / 56, Material(albedo=(1.0, 1.0, 1.0), interreflect=True)))
    surfaces.append(Sphere(np.array([-20.0, 60.0, 980.0]), 70.0,
                           Material(albedo=(0.3, 0.32, 0.35), specular=4.0, shininess=120.0)))
    return Scene("corner", surfaces, "concave corner with inter-reflection and a glossy sphere")


SCENES: dict[str, Callable[[int], Scene]] = {
    "plane": scene_plane,
    "spheres": scene_spheres,
    "corner": scene_corner,
    "bunny": scene_bunny,
    "teapot": scene_teapot,
    "spot": scene_spot,
    "fandisk": scene_fandisk,
}


def build_scene(name: str, seed: int = 0) -> Scene:
    """A named scene; unknown names are an :class:`InputError` listing the known ones."""
    if name not in SCENES:
        raise InputError("--scene", f"unknown scene {name!r}; known: {', '.join(sorted(SCENES))}")
    return SCENES[name](seed)
