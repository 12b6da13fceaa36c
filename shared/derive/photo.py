"""Base colour from the views' photographs at their own resolution.

Each surface point (a texel's, or a master vertex's) takes its albedo from the views that see it:

- **albedo per photograph pixel**: the view's white and black frames at the pixel the point
  projects to (bilinear in linear light), divided by the projector's irradiance at the point
  itself (:func:`shared.scan.albedo.estimate_albedo` with the view's radiometry from its rig), so
  the colour comes from the photographs at the camera's resolution and not from the cloud's
  samples; one reference distance for every view, so the views agree in scale;
- **visibility** against the mesh: a ray from the view's camera centre (its pose in
  ``registration.json``) to the point must not hit the mesh before it (Open3D ray casting: a
  z-buffer per view without rasterising one);
- **weights**: the cosine to the camera times the cosine to the projector (angle), the inverse
  square of the camera distance relative to the view's median (distance: a nearer view has the
  finer footprint) and the white-minus-black contrast relative to the view's median (what the
  decoder's confidence is made of: a dim, noisy pixel decodes badly and colours badly);
- **highlights** rejected by disagreement: a view whose luminance is above ``specular_ratio``
  times the weighted median of the views that see the point is left out (a highlight follows the
  projector and camera, so it is seen by one view, not all);
- **brightness levelled across seams**, in two steps: one gain per view (each view's gain is the
  median ratio, over the points it shares with others, of the consensus to its own estimate; two
  rounds, geometric mean 1), then a smooth per-view colour correction over the surface solved as
  one sparse least-squares problem (Waechter, Moehrle, Goesele, 'Let There Be Color!', ECCV 2014:
  views agree where they overlap, corrections vary smoothly; :mod:`shared.derive._seams`).

Points no view sees keep the cloud's colour (the caller's fallback).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from shared.core.errors import InputError
from shared.core.files import read_json
from shared.formats.images import read_colour
from shared.formats.rig import Rig, load_rig
from shared.formats.scanset import ScanSet, load_scanset
from shared.scan.albedo import estimate_albedo, params_for_rig
from shared.scan.pipeline import ingest_stage

log = logging.getLogger(__name__)

__all__ = ["PhotoParams", "PhotoSource", "load_photo_source"]

_LUMA = np.array([0.2126, 0.7152, 0.0722])


@dataclass(frozen=True)
class PhotoParams:
    """specular_ratio : a view brighter than this times the points' weighted median luminance is a
    highlight (the weighted median; with highlight_vote_share, the median of the views weighing at
    least that share of the heaviest there, one vote each: weighted, a highlight in the heaviest
    view is its own reference. Measured at 0.3 on 8-view 480x360 sets, 1024 px: the glossy teapot's
    baked projector reflections fade, its colour jump across view borders 0.045 -> 0.032 and error
    per texel 0.155 -> 0.153, but the matte bunny's error rises 0.097 -> 0.099 and spot's
    0.0935 -> 0.0939: off by default). min_cos_camera : smallest cosine between the normal and the direction to the camera
    (about 78 degrees). visibility_tol_mm : how far in front of the point the mesh may be hit and
    still count as the point itself (the level's facets lie off the true surface by its
    simplification error). feather : a view's weight falls to zero over this much cosine above the
    camera's and the projector's cut-off angles (0: a step). gain_samples : surface points the per-view gains and corrections are
    solved on. seam_levelling : solve the smooth per-view corrections after the gains.
    seam_proxy_faces : faces of the coarse surface they are solved on (their resolution).
    seam_smoothness : weight of their smoothness against the views' agreement. seam_max_factor :
    largest correction either way (a factor on the view's albedo). seam_anchor : how firmly a view
    keeps its colour where it weighs much (:mod:`shared.derive._seams`). specular_lobe_deg : a
    view sees a point in its mirror configuration when the surface normal lies within this angle
    of the half-vector between the directions to the view's camera and to its projector: the one
    place a glossy surface throws the projector's light into the camera. Such views are left out
    of the reference a highlight is judged against wherever another view sees the point (the
    reference is then never the highlight itself), and points only such views see are counted
    (``highlight_risk_share``): their colour may be a highlight. 0: no mirror test."""

    specular_ratio: float = 1.35
    specular_lobe_deg: float = 20.0
    min_cos_camera: float = 0.2
    visibility_tol_mm: float = 1.0
    gain_samples: int = 60_000
    highlight_vote_share: float | None = None
    feather: float = 0.15
    seam_levelling: bool = True
    seam_proxy_faces: int = 16_000
    seam_smoothness: float = 0.1
    seam_max_factor: float = 1.6
    seam_anchor: float = 1.0


@dataclass
class _View:
    name: str
    rig: Rig
    white: np.ndarray  # (H, W, 3) uint8
    black: np.ndarray
    R: np.ndarray  # view -> set rotation (3, 3)
    T: np.ndarray  # (3,) mm
    scale_mm: float
    gain: float = 1.0

    def projector_centre_mm(self) -> np.ndarray:
        """(3,) the projector's centre in this view's camera frame, mm (X_p = R X_c + T)."""
        return -np.asarray(self.rig.R, np.float64).T @ np.asarray(self.rig.T, np.float64).ravel() * self.scale_mm


@dataclass
class PhotoSource:
    """The photographed views of a merge with their poses; :meth:`colour` gives linear albedo."""

    views: list[_View]
    params: PhotoParams = field(default_factory=PhotoParams)
    reference_distance_mm: float = 1.0
    stats: dict = field(default_factory=dict)
    # The seam corrections (a KD-tree of the proxy's vertices, (V, P, 3) factors), once solved.
    _corrections: tuple | None = field(default=None, init=False, repr=False)

    def _per_view(self, P: np.ndarray, N: np.ndarray, scene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(V, n, 3) linear albedo before gains, (V, n) weights (0: not seen) and (V, n) bool the
        views' mirror configurations (see ``specular_lobe_deg``) of points P, N (set frame, mm)."""
        import open3d as o3d

        V, n = len(self.views), len(P)
        alb = np.zeros((V, n, 3), np.float32)
        wts = np.zeros((V, n), np.float32)
        lobe = np.zeros((V, n), np.bool_)
        cos_lobe = np.cos(np.radians(self.params.specular_lobe_deg))
        for k, view in enumerate(self.views):
            s = view.scale_mm
            # The view's camera frame, mm (einsum: no BLAS threads for a 3x3 product).
            X = np.einsum("ij,jk->ik", P - view.T, view.R)
            Nv = np.einsum("ij,jk->ik", N, view.R)
            cam = view.rig.camera
            z = X[:, 2]
            front = z > 1e-6
            to_cam = -X / np.maximum(np.linalg.norm(X, axis=1, keepdims=True), 1e-12)
            cos_c = np.einsum("ij,ij->i", Nv, to_cam)
            ok = front & (cos_c > self.params.min_cos_camera)
            uv = _project(X[ok], np.asarray(cam.K, np.float64), np.asarray(cam.dist, np.float64).ravel())
            idx = np.flatnonzero(ok)
            inside = (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] <= cam.width - 1) & (uv[:, 1] <= cam.height - 1)
            idx, uv = idx[inside], uv[inside]
            if len(idx) == 0:
                continue
            # Visibility: the ray from the camera centre to the point meets nothing closer.
            centre = view.T
            d = P[idx] - centre
            dist = np.linalg.norm(d, axis=1)
            rays = np.concatenate([np.repeat(centre[None], len(idx), 0), d / dist[:, None]], 1).astype(np.float32)
            t_hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
            seen = t_hit >= dist - self.params.visibility_tol_mm
            idx, uv, dist = idx[seen], uv[seen], dist[seen]
            if len(idx) == 0:
                continue
            white = _bilinear_u8(view.white, uv)
            black = _bilinear_u8(view.black, uv)
            prm = replace(params_for_rig(view.rig), reference_distance=self.reference_distance_mm / s)
            est = estimate_albedo(white, black, X[idx] / s, Nv[idx], view.rig, prm)
            good = est.weight > 0
            idx, dist = idx[good], dist[good]
            a = est.albedo[good]
            sig = (prm.response.lut()[white[good]] - prm.response.lut()[black[good]]) @ _LUMA
            contrast = sig / max(float(np.median(sig)), 1e-6)
            w = cos_c[idx] * est.weight[good] * (np.median(dist) / dist) ** 2 * np.clip(contrast, 0.0, 2.0)
            if self.params.feather > 0:
                # Down to zero at the angles where a view stops counting, not a step there.
                f = self.params.feather
                w *= np.clip((cos_c[idx] - self.params.min_cos_camera) / f, 0.0, 1.0)
                w *= np.clip((est.weight[good] - prm.min_cos) / f, 0.0, 1.0)
            alb[k, idx] = a
            wts[k, idx] = np.maximum(w, 0.0)
            if self.params.specular_lobe_deg > 0:
                pc = view.projector_centre_mm()
                Xi = X[idx]
                to_proj = pc - Xi
                half = to_cam[idx] + to_proj / np.maximum(np.linalg.norm(to_proj, axis=1, keepdims=True), 1e-12)
                cos_h = np.einsum("ij,ij->i", Nv[idx], half) / np.maximum(np.linalg.norm(half, axis=1), 1e-12)
                lobe[k, idx] = cos_h > cos_lobe
        return alb, wts, lobe

    def _reject(self, a: np.ndarray, wts: np.ndarray, lobe: np.ndarray) -> tuple[np.ndarray, int]:
        """(V, n) weights with highlights left out (zero), and how many were, of albedo a (V, n, 3),
        weights ``wts`` and mirror configurations ``lobe`` (V, n)."""
        lum = a @ _LUMA  # (V, n)
        w = wts.copy()
        share = self.params.highlight_vote_share
        if share is None:
            # The reference leaves out the views in their mirror configuration where another view
            # sees the point: weighted, the view facing a glossy point (the heaviest) would be its
            # own highlight's reference and never be left out.
            off = np.where(lobe, 0.0, w)
            med = _weighted_median(lum, np.where((off > 0).any(axis=0)[None], off, w))
        else:
            # One vote for each view weighing at least ``share`` of the heaviest at the point:
            # weighted, the view a highlight is in (often the one facing the point, so the
            # heaviest) would be its own reference and never be left out.
            med = _weighted_median(lum, (w >= share * w.max(axis=0, keepdims=True)) & (w > 0))
        several = (w > 0).sum(axis=0) >= 2
        glint = (lum > self.params.specular_ratio * med[None]) & (w > 0) & several[None]
        w[glint] = 0.0
        return w, int(glint.sum())

    def _combine(self, alb: np.ndarray, wts: np.ndarray, lobe: np.ndarray,
                 gains: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        """Weighted mean over views after gains and highlight rejection: (n, 3), seen (n,), rejected count."""
        out, seen, rejected, _ = self._blend(alb * gains[:, None, None], wts, lobe)
        return out, seen, rejected

    def _blend(self, a: np.ndarray, wts: np.ndarray, lobe: np.ndarray) -> tuple[np.ndarray, np.ndarray, int, np.ndarray]:
        """_combine of albedo a (V, n, 3) with its gains applied; also the weights (V, n) used."""
        w, rejected = self._reject(a, wts, lobe)
        total = w.sum(axis=0)
        seen = total > 0
        out = np.einsum("vn,vnc->nc", w, a) / np.maximum(total, 1e-30)[:, None]
        return out.astype(np.float32), seen, rejected, w

    def solve_gains(self, P: np.ndarray, N: np.ndarray, scene,
                    surface: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """Per-view gains, then (with ``surface``, the level's vertices (V, 3) mm and faces (F, 3),
        and ``params.seam_levelling``) the smooth per-view corrections, on a sample of the surface
        points P (n, 3) mm with unit normals N (n, 3) (see the module docstring)."""
        rng = np.random.default_rng(0)
        if len(P) > self.params.gain_samples:
            pick = rng.choice(len(P), self.params.gain_samples, replace=False)
            P, N = P[pick], N[pick]
        # One reference distance for all views (the median distance from view 0's projector), so
        # their albedos share a scale before the gains level what remains.
        v0 = self.views[0]
        proj = v0.projector_centre_mm()
        self.reference_distance_mm = float(np.median(np.linalg.norm(P - (v0.R @ proj + v0.T), axis=1)))
        alb, wts, lobe = self._per_view(P, N, scene)
        gains = np.ones(len(self.views))
        for _ in range(2):
            cons, seen, _ = self._combine(alb, wts, lobe, gains)
            lc = cons @ _LUMA
            for k in range(len(self.views)):
                shared = (wts[k] > 0) & seen & ((wts > 0).sum(axis=0) >= 2)
                own = alb[k, shared] @ _LUMA * gains[k]
                if shared.sum() >= 50:
                    gains[k] *= float(np.median(lc[shared] / np.maximum(own, 1e-6)))
            gains /= float(np.exp(np.mean(np.log(gains))))
        for view, g in zip(self.views, gains, strict=True):
            view.gain = float(g)
        self.stats["gains"] = {v.name: round(v.gain, 4) for v in self.views}
        self._corrections = None
        if surface is None or not self.params.seam_levelling or len(self.views) < 2:
            return
        from scipy.spatial import cKDTree

        from shared.derive._seams import proxy_surface, solve_corrections

        t0 = time.perf_counter()
        pv, edges = proxy_surface(surface[0], surface[1], self.params.seam_proxy_faces)
        tree = cKDTree(pv)
        a = alb * gains[:, None, None].astype(np.float32)
        w, _ = self._reject(a, wts, lobe)
        g, st = solve_corrections(a, w, tree.query(P)[1], edges, len(pv), self.params.seam_smoothness,
                                  self.params.seam_max_factor, self.params.seam_anchor)
        self._corrections = (tree, np.exp(g))
        self.stats["seams"] = {**st, "proxy_vertices": int(len(pv)), "seconds": round(time.perf_counter() - t0, 3)}

    def _corrected(self, alb: np.ndarray, P: np.ndarray) -> np.ndarray:
        """alb (V, n, 3) times the views' seam corrections at P (n, 3), interpolated from the
        proxy's three nearest vertices (inverse distance)."""
        corr = self._corrections
        if corr is None:
            return alb
        tree, factor = corr
        d, nb = tree.query(P, k=3)
        w = 1.0 / np.maximum(d, 1e-9)
        w = (w / w.sum(axis=1, keepdims=True)).astype(np.float32)
        for k in range(len(alb)):
            alb[k] *= np.einsum("nj,njc->nc", w, factor[k][nb])
        return alb

    def colour(self, P: np.ndarray, N: np.ndarray, scene,
               return_view: bool = False) -> tuple[np.ndarray, ...]:
        """Linear albedo (n, 3) float32 of points P (n, 3) mm with unit normals N (n, 3), set frame,
        and (n,) bool where some view saw the point; ``scene`` an Open3D RaycastingScene of the mesh.
        With ``return_view`` also (n,) int the view that weighs most at each point (-1: none) and
        (n,) uint32 the set of views blended there (bit k: view k; views beyond 32 are not marked)."""
        P = np.asarray(P, np.float64)
        alb, wts, lobe = self._per_view(P, np.asarray(N, np.float64), scene)
        gains = np.array([v.gain for v in self.views], np.float32)
        alb = self._corrected(alb * gains[:, None, None], P)
        out, seen, rejected, w = self._blend(alb, wts, lobe)
        self.stats["highlights_rejected"] = self.stats.get("highlights_rejected", 0) + rejected
        # Points whose colour comes only from views in their mirror configuration: it may be a
        # highlight (no other view to judge it against).
        risky = seen & ~((w > 0) & ~lobe).any(axis=0)
        self.stats["points_coloured"] = self.stats.get("points_coloured", 0) + int(seen.sum())
        self.stats["highlight_risk_points"] = self.stats.get("highlight_risk_points", 0) + int(risky.sum())
        if not return_view:
            return out, seen
        used = ((w > 0) << np.arange(len(w), dtype=np.uint32)[:, None]).sum(axis=0, dtype=np.uint32)
        return out, seen, np.where(seen, np.argmax(w, axis=0), -1), used


def _project(X: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """(n, 2) pixel coordinates of camera-frame points X (n, 3) (in front of it): OpenCV's model,
    here in numpy for its five usual coefficients (cv2.projectPoints took a third of the
    photograph bake's CPU: 0.7 s for half a million points), cv2 for the rational ones."""
    if len(dist) > 5 and np.any(dist[5:] != 0):
        return cv2.projectPoints(X.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, dist)[0].reshape(-1, 2)
    k1, k2, p1, p2, k3 = (float(v) for v in np.concatenate([dist, np.zeros(5)])[:5])
    x = X[:, 0] / X[:, 2]
    y = X[:, 1] / X[:, 2]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]], axis=1)


def _bilinear_u8(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(n, 3) uint8 bilinear samples of an (H, W, 3) uint8 image at float pixel centres uv (n, 2)."""
    H, W = img.shape[:2]
    x0 = np.clip(np.floor(uv[:, 0]).astype(np.int64), 0, W - 2)
    y0 = np.clip(np.floor(uv[:, 1]).astype(np.int64), 0, H - 2)
    fx = (uv[:, 0] - x0).astype(np.float32)[:, None]
    fy = (uv[:, 1] - y0).astype(np.float32)[:, None]
    # The four neighbours gathered as bytes, then converted (not the whole image per call).
    v = ((img[y0, x0].astype(np.float32) * (1 - fx) + img[y0, x0 + 1].astype(np.float32) * fx) * (1 - fy)
         + (img[y0 + 1, x0].astype(np.float32) * (1 - fx) + img[y0 + 1, x0 + 1].astype(np.float32) * fx) * fy)
    return np.clip(np.rint(v), 0, 255).astype(np.uint8)


def _weighted_median(values: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(n,) weighted median over axis 0 of (V, n) values (NaN-free), ignoring zero weights."""
    order = np.argsort(np.where(weights > 0, values, np.inf), axis=0)
    v = np.take_along_axis(values, order, 0)
    w = np.take_along_axis(weights, order, 0)
    c = np.cumsum(w, axis=0)
    half = 0.5 * c[-1]
    pos = np.minimum((c < half[None]).sum(axis=0), len(values) - 1)
    return np.take_along_axis(v, pos[None], 0)[0]


def _pose(entry: dict, path: Path) -> tuple[np.ndarray, np.ndarray]:
    """A registered view's (R (3, 3), T (3,)) from registration.json, checked."""
    try:
        R = np.asarray(entry["R"], np.float64)
        T = np.asarray(entry["T"], np.float64)
    except (KeyError, TypeError, ValueError):
        raise InputError(path, f"view {entry.get('name')!r}: R and T must be numbers") from None
    if R.shape != (3, 3) or T.shape != (3,) or not (np.isfinite(R).all() and np.isfinite(T).all()) \
            or abs(np.linalg.det(R) - 1.0) > 1e-3:
        raise InputError(path, f"view {entry.get('name')!r}: R must be a 3x3 rotation and T 3 finite numbers")
    return R, T


def load_photo_source(merge_dir: Path, scanset_dir: Path | None = None,
                      params: PhotoParams | None = None) -> tuple[PhotoSource | None, str | None]:
    """The photographed views of a merge: its ``registration.json`` poses and, from the scan set
    (``scanset_dir`` or the one the merge's ``report.json`` names), each captured view's white and
    black frames and rig. Returns (source, None), or (None, why) when there is no photograph to
    bake from (cloud views only, the scan set gone): the caller falls back and says why."""
    merge_dir = Path(merge_dir)
    reg_path = merge_dir / "registration.json"
    if not reg_path.is_file():
        return None, "no registration.json beside the master"
    reg = read_json(reg_path, "the merge's registration is missing")
    if scanset_dir is None:
        rep = merge_dir / "report.json"
        named = read_json(rep, "the merge's report is missing").get("scanset") if rep.is_file() else None
        if not named:
            return None, "the merge's report names no scan set"
        scanset_dir = Path(named)
    try:
        scanset = load_scanset(Path(scanset_dir))
    except InputError as exc:
        return None, f"the scan set cannot be read: {exc.problem}"
    entries = {e.get("name"): e for e in reg.get("views", []) if isinstance(e, dict)}
    try:
        views = _photographed_views(scanset, entries, reg_path)
    except InputError as exc:
        return None, f"a view's photographs cannot be read: {exc.problem}"
    if not views:
        return None, "no registered captured view has photographs"
    return PhotoSource(views=views, params=params or PhotoParams()), None


def _photographed_views(scanset: ScanSet, entries: dict, reg_path: Path) -> list[_View]:
    views: list[_View] = []
    for spec in scanset.views:
        e = entries.get(spec.name)
        if spec.kind != "capture" or e is None or not e.get("registered"):
            continue
        capture = ingest_stage(spec.path, spec.rig)
        if capture.rig is None:
            continue
        rig = load_rig(capture.rig)
        R, T = _pose(e, reg_path)
        size = (rig.camera.width, rig.camera.height)
        views.append(_View(name=spec.name, rig=rig, white=read_colour(capture.white, size),
                           black=read_colour(capture.black, size), R=R, T=T, scale_mm=float(spec.scale_mm)))
    return views
