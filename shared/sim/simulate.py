"""The virtual rig: physically plausible synthetic Gray-code captures with per-pixel ground truth.

In: a :class:`~shared.sim.scenes.Scene` (surfaces in the camera frame, mm), a :class:`~shared.formats.rig.Rig`
(:func:`make_rig` builds a realistic one) and :class:`ImagingParams`. Out: a ``graycode-v1``
capture folder (``capture.json``, ``rig.json``, ``white.png``, ``black.png``, ``col_NN[_inv].png``,
``row_NN[_inv].png``) plus ``truth.npz`` with, per camera pixel (H, W):

- ``depth`` float32: camera Z in mm, NaN where no surface;
- ``points`` (H, W, 3) float32: camera-frame point in mm (NaN where no surface);
- ``normals`` (H, W, 3) float32: unit surface normal facing the camera;
- ``proj_col``, ``proj_row`` float32: continuous projector pixel coordinates of the point,
  through the projector's distortion (OpenCV: projector column ``c`` spans ``[c - 0.5, c + 0.5)``);
- ``lit`` bool: surface seen by the camera AND lit by the projector (inside its frame, facing it,
  not in its shadow);
- ``surface`` int16: index of the scene surface seen (-1 none);
- ``labels`` int8: what the pixel sees, the surface's label (:mod:`shared.sim.scenes`): -1 none,
  0 object, 1 turntable plate, 2 support (table top or floor), 3 turntable base, 4 backdrop;
- ``albedo`` (H, W, 3) float32: the linear RGB diffuse albedo (0..1) the image was rendered with
  (area-filtered over the pixel on planes; NaN where no surface);
- ``irradiance`` float32: the linear white-minus-black signal per unit albedo, in fractions of full
  scale: ``(1 - black_level) * cam_vignetting * frame * G`` with ``G = projector_power * cos(theta)
  * (1000 mm / d)^2 * cos^3(off-axis angle) * (1 + projector_vignetting * r^2)`` (``d`` the distance
  from the projector's centre, ``r`` the undistorted normalised radius in the projector's frame,
  ``frame`` the blurred edge of the projector's image, ``cam_vignetting`` cos^4 of the camera
  ray's angle); 0 where not lit, NaN where no surface. :func:`sim_radiometry` states the same for
  a rig's ``radiometry``;
- ``response`` (0-d str): the camera response the images went through (:mod:`shared.sim.response`).

So ``linearise(white) - linearise(black) = albedo * irradiance`` (grey cameras: the albedo's luma
0.299 R + 0.587 G + 0.114 B) up to sensor noise, camera blur, the specular lobe of glossy
materials and inter-reflection: dividing out the projector's irradiance recovers the albedo.

Image formation (per pattern, linear, in fractions of the sensor's full scale): projector irradiance
with cos(theta), inverse-square falloff, cos^3 and lens vignetting, projector black level, defocus blur of the pattern that grows
with distance from the projector's focus (Gaussian in projector pixels, tabulated per blur level),
shadows by a projector shadow map, ambient light, textured and coloured albedo with pixel-area
filtering, a Phong specular lobe that can saturate, subsurface scattering (extra pattern blur on
translucent materials), one bounce of diffuse inter-reflection between
planes that ask for it, camera vignetting (cos^4), optical blur, shot and read noise, full-well
clipping, the camera's response curve (sRGB by default) and 8- or 16-bit quantisation; grey or
colour (BGR PNG) images. Both devices have lens
distortion: camera pixels are traced along their exact (undistorted) rays, and projector
coordinates go through the projector's distortion model.

Public API::

    rig = make_rig(camera_size=(2048, 1536), projector_size=(1024, 768), seed=0)
    scene = build_scene("bunny")          # SCENES: plane, spheres, corner, bunny, teapot, spot, fandisk
    board = TexturedPlane.chessboard(R, t, inner_corners=(9, 7), square_size=30.0)
    scene = Scene("board", [board])       # board.to_camera(board.chessboard_corners()): true corners
    capture = simulate_capture(scene, rig, out_dir, seed=0, imaging=ImagingParams(inverses=True))
    truth = compute_truth(scene, rig)     # the truth arrays only, no images
    images, truth = render_pattern_images(scene, rig, seed=0)   # in memory, for small sizes
    capture = simulate_named("bunny", out_dir, size=(2048, 1536), seed=0)   # ``graylight simulate``
    truth = load_truth(capture.root)

``seed`` of :func:`simulate_capture` drives only the sensor noise; scenes and rigs take their own
seeds. The same arguments always give byte-identical files.

:class:`ImagingParams` and the per-capture set-up (ray casting, shadow map, shading, blur tables,
inter-reflection) are in :mod:`shared.sim._imaging`; this module renders the pattern images from
that set-up and writes the capture.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
import time
from collections.abc import Collection
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from shared.core.errors import InputError
from shared.formats.capture import Capture, load_capture, write_capture
from shared.formats.rig import Rig, save_rig
from shared.scan.graycode import capture_for_names, pattern_sequence, stripe_bits
from shared.sim._imaging import ImagingParams, _profile_table, _Profiles, _Render, _render_setup
from shared.sim.raycast import compose_image, sensor_readout
from shared.sim.response import check_response
from shared.sim.rigs import make_rig
from shared.sim.scenes import (
    SCENES,
    Material,
    MeshObject,
    Scene,
    Sphere,
    TexturedPlane,
    build_scene,
)
from shared.sim.truth import TRUTH_FILE, Truth, load_truth

__all__ = [
    "SCENES",
    "TRUTH_FILE",
    "ImagingParams",
    "Material",
    "MeshObject",
    "Scene",
    "Sphere",
    "TexturedPlane",
    "Truth",
    "build_scene",
    "compute_truth",
    "load_truth",
    "make_rig",
    "render_pattern_images",
    "simulate_capture",
    "sim_radiometry",
    "simulate_named",
]

log = logging.getLogger(__name__)

RIG_FILE = "rig.json"



# ---------------------------------------------------------------------------------------------
# Images


def _pattern_table(rig: Rig, imaging: ImagingParams, pg: _Profiles, sigmas: np.ndarray,
                   axis: str, bit: int, inverse: bool) -> tuple[str, np.ndarray]:
    """The varying axis (``"u"`` or ``"v"``) of one projector image and its blurred profile table (L, n).

    A projector image is separable: stripes along one axis times the projector frame along the other.
    """
    w, h = rig.projector.width, rig.projector.height
    b = imaging.black_level
    if axis == "columns":
        s = stripe_bits(w, bit)
        return "u", _profile_table(b + (1 - b) * (~s if inverse else s), sigmas, pg, pg.nu)
    if axis == "rows":
        s = stripe_bits(h, bit)
        return "v", _profile_table(b + (1 - b) * (~s if inverse else s), sigmas, pg, pg.nv)
    if axis == "white":
        return "u", _profile_table(np.ones(w), sigmas, pg, pg.nu)
    if axis == "black":
        return "u", _profile_table(np.full(w, b), sigmas, pg, pg.nu)
    raise ValueError(f"unknown pattern axis {axis!r}")


def _render_image(r: _Render, axis: str, bit: int, inverse: bool, noise_seed: int) -> np.ndarray:
    """One camera image (H, W) or (H, W, 3) BGR, uint8/uint16, of the projector showing one pattern."""
    sh = r.shading
    assert sh is not None
    im = r.imaging
    cam = r.rig.camera
    nc = sh.A.shape[1]
    which, table = _pattern_table(r.rig, im, r.profiles, sh.sigmas, axis, bit, inverse)
    img = np.zeros((cam.height * cam.width, nc), np.float32)
    if which == "u":
        compose_image(sh.index, sh.A, sh.B, sh.off_u, sh.frac_u, table, sh.frame_v, img)
    else:
        compose_image(sh.index, sh.A, sh.B, sh.off_v, sh.frac_v, table, sh.frame_u, img)
    if sh.inter is not None:
        ir = sh.inter
        # Senders: the same pattern at each patch's subsamples (frame edges ignored: patches lie inside).
        k = 0 if which == "u" else 1
        t = table.ravel()
        o, f = ir.sender_off[k], ir.sender_frac[k]
        Ps = (t[o] + f * (t[o + 1] - t[o])).reshape(ir.sender_G.shape)
        E = (ir.sender_G * Ps).mean(axis=1)
        Eind = ir.F @ (ir.sender_albedo * E[:, None])  # (M, C) indirect irradiance at patch centres
        for (off, gx, _), (rows, i00, wx, wy) in zip(ir.grids, ir.pix, strict=True):
            g = Eind[off:]
            e = ((1 - wy)[:, None] * ((1 - wx)[:, None] * g[i00] + wx[:, None] * g[i00 + 1])
                 + wy[:, None] * ((1 - wx)[:, None] * g[i00 + gx] + wx[:, None] * g[i00 + gx + 1]))
            img[sh.index[rows]] += ir.pix_coef[rows] * e
    img = img.reshape(cam.height, cam.width, nc)
    if im.camera_blur > 0:
        img = cv2.GaussianBlur(img, (0, 0), im.camera_blur)
        if img.ndim == 2:
            img = img[:, :, None]
    out = sensor_readout(img, im.full_well, im.read_noise, im.bits, noise_seed, response_codes=r.response_codes,
                         noise=im.noise)
    if nc == 3:
        return np.ascontiguousarray(out[:, :, ::-1])  # RGB -> BGR for cv2.imwrite
    return out[:, :, 0]


def _write_png(path: Path, img: np.ndarray) -> None:
    # Fast zlib level with Huffman-only coding: several times faster than the default for noisy images.
    params = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY]
    if not cv2.imwrite(str(path), img, params):
        raise OSError(f"could not write {path}")


def _noise_seed(seed: int, k: int) -> int:
    return int(np.random.SeedSequence([seed, k]).generate_state(1)[0] & 0x7FFFFFFF)


def render_pattern_images(
    scene: Scene,
    rig: Rig,
    *,
    seed: int = 0,
    imaging: ImagingParams | None = None,
    names: Collection[str] | None = None,
) -> tuple[dict[str, np.ndarray], Truth]:
    """Capture images in memory (name -> image, names as :func:`shared.scan.graycode.pattern_sequence`) and the truth.

    ``names`` picks some of the images (e.g. ``{"white.png", "col_09.png"}``); each image is the
    same as in the full capture with the same seed. Meant for small sizes and tests;
    :func:`simulate_capture` renders one image at a time to disk instead.
    """
    imaging = imaging or ImagingParams()
    r = _render_setup(scene, rig, imaging)
    images = {}
    for k, (name, axis, bit, inv, _) in enumerate(
        pattern_sequence(rig.projector.width, rig.projector.height, rows=imaging.rows)
    ):
        if (inv and not imaging.inverses) or (names is not None and name not in names):
            continue
        images[name] = _render_image(r, axis, bit, inv, _noise_seed(seed, k))
    return images, r.truth


def compute_truth(scene: Scene, rig: Rig, imaging: ImagingParams | None = None) -> Truth:
    """Ground truth only (no images): depth, points, normals, projector coordinates, lit mask."""
    return _render_setup(scene, rig, imaging or ImagingParams(), with_shading=False).truth


def sim_radiometry(imaging: ImagingParams | None = None) -> dict[str, object]:
    """How this simulator forms images, as a rig's ``radiometry`` block (issue 23's rig contract):
    the camera's response, the projector's cos^3 falloff, the camera's cos^4 vignetting when it is
    on, and the projector lens's vignetting ``[k1]`` of ``1 + k1 r^2`` (r the undistorted
    normalised projector radius). A scan divides them out to recover the albedo."""
    imaging = imaging or ImagingParams()
    return {"camera_response": imaging.response, "projector_falloff_cos_power": 3.0,
            "camera_falloff_cos_power": 4.0 if imaging.vignetting else 0.0,
            "projector_vignetting": [float(imaging.projector_vignetting)]}


def _check_size(camera_size: tuple[int, int]) -> None:
    w, h = camera_size
    if not (16 <= w <= 20000 and 16 <= h <= 20000):
        raise InputError("--size", f"camera size {w}x{h} is outside 16..20000 pixels per side")


def simulate_capture(
    scene: Scene,
    rig: Rig,
    out_dir: str | os.PathLike[str],
    *,
    seed: int = 0,
    imaging: ImagingParams | None = None,
    overwrite: bool = False,
    write_truth: bool = True,
) -> Capture:
    """Render a full ``graycode-v1`` capture of ``scene`` into ``out_dir`` (with ``rig.json`` and ``truth.npz``).

    The folder is assembled under a temporary name beside ``out_dir`` and renamed when complete,
    so a failure leaves nothing half-written. An existing non-empty ``out_dir`` is an
    :class:`InputError` unless ``overwrite`` and it holds a capture (then it is replaced). Images are
    rendered and written one at a time (PNG, low compression), so memory stays a few times the size
    of one image's float buffers even at 15 MP (about 1.9 GB peak there). ``seed`` drives the sensor noise; the same inputs give identical files.

    Returns the written capture (as :func:`shared.formats.capture.load_capture` would read it).
    """
    imaging = imaging or ImagingParams()
    if imaging.bits not in (8, 16):
        raise InputError("bits", f"must be 8 or 16, got {imaging.bits}")
    check_response(imaging.response)
    _check_size((rig.camera.width, rig.camera.height))
    out = Path(out_dir).absolute()
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        if not overwrite:
            raise InputError(out, "output folder exists and is not empty")
        if not (out / "capture.json").is_file():
            # Replacing is for re-running a simulation, never for wiping an unrelated folder.
            raise InputError(out, "output folder exists and does not hold a capture; refusing to replace it")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
    umask = os.umask(0)
    os.umask(umask)
    tmp.chmod(0o777 & ~umask)  # mkdtemp makes it private; the capture is an ordinary folder
    try:
        t0 = time.perf_counter()
        r = _render_setup(scene, rig, imaging)
        t1 = time.perf_counter()
        seq = pattern_sequence(rig.projector.width, rig.projector.height, rows=imaging.rows)
        # PNG encoding (OpenCV releases the GIL) overlaps with rendering the next image; at most
        # two images wait, so memory stays bounded at 15 MP.
        with ThreadPoolExecutor(max_workers=1) as pool:
            pending: list[Future[None]] = []
            for k, (name, axis, bit, inv, _) in enumerate(seq):
                if inv and not imaging.inverses:
                    continue
                img = _render_image(r, axis, bit, inv, _noise_seed(seed, k))
                pending.append(pool.submit(_write_png, tmp / name, img))
                while len(pending) > 1:
                    pending.pop(0).result()
            for f in pending:
                f.result()
        t2 = time.perf_counter()
        save_rig(replace(rig, radiometry=rig.radiometry or sim_radiometry(imaging)), tmp / RIG_FILE)
        if write_truth:
            r.truth.save(tmp / TRUTH_FILE)
        capture = capture_for_names(tmp, rig.projector.width, rig.projector.height, rows=imaging.rows,
                                    rig=tmp / RIG_FILE)
        extra = {"simulated": {"scene": scene.name, "description": scene.description, "seed": seed,
                               "truth": TRUTH_FILE if write_truth else None,
                               "imaging": {k: v for k, v in imaging.__dict__.items()}}}
        capture = replace(capture, extra=extra)
        if not imaging.inverses:
            capture = replace(capture, columns=tuple(replace(e, inverse=None) for e in capture.columns),
                              rows=tuple(replace(e, inverse=None) for e in capture.rows))
        write_capture(capture)
        if out.exists():
            shutil.rmtree(out) if out.is_dir() else out.unlink()
        os.replace(tmp, out)
        log.info("virtual rig: %s %dx%d: setup %.2fs, %d images %.2fs", scene.name, rig.camera.width,
                 rig.camera.height, t1 - t0, len(seq), t2 - t1)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return load_capture(out)


def simulate_named(
    scene: str,
    out_dir: str | os.PathLike[str],
    *,
    size: tuple[int, int] = (2048, 1536),
    projector: tuple[int, int] = (1024, 768),
    seed: int = 0,
    imaging: ImagingParams | None = None,
    overwrite: bool = False,
) -> Capture:
    """``graylight simulate``: a named scene (:data:`SCENES`) with :func:`make_rig` of the given sizes."""
    _check_size(size)
    sc = build_scene(scene, seed=seed)
    rig = make_rig(camera_size=size, projector_size=projector, seed=seed)
    return simulate_capture(sc, rig, out_dir, seed=seed, imaging=imaging, overwrite=overwrite)
