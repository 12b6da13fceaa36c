"""A Smithsonian Voyager scene (``scene.svx.json``) for one published object.

One model in millimetres whose Web3D derivatives are the quality levels present (each a GLB, with
``byteSize``, ``numFaces`` and ``imageSize``); a single view's cloud is a GLB of points (Voyager
loads a derivative's ``Model`` asset) with the PLY beside it as a ``Points`` asset. The model's
``rotation`` and ``translation`` stand the object on the origin with the turntable axis up (+Y,
Voyager's up): :func:`upright_pose`. A camera and four lights frame it; ``metas[0]`` holds the
title, collection and identifier (``collection``) and the paradata (``process``). Voyager shows
the title as HTML, so those strings are HTML-escaped in the scene (``&lt;b&gt;`` shows as ``<b>``);
``qa.json`` and the paradata keep them verbatim.

Schemas: ``shared/reference/voyager-svx-schema`` (draft-07; ``document.schema.json`` refers to
the other four), checked in the tests.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from html import escape
from typing import Any

import numpy as np

from shared.publish.glb import GlbInfo

__all__ = ["SceneAsset", "build_scene", "upright_pose"]

SVX_VERSION = "1.0"


@dataclass(frozen=True)
class SceneAsset:
    """One derivative level: its quality, its GLB (measured) and optional extra assets (``uri``, ``type``, bytes)."""

    quality: str
    uri: str
    info: GlbInfo
    extra: tuple[tuple[str, str, int], ...] = ()


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def upright_pose(points: np.ndarray, axis: Mapping[str, Any] | None) -> tuple[np.ndarray, np.ndarray, str]:
    """The rotation ``R`` (3x3) and translation ``t`` (mm) taking the model's frame (view 0's camera:
    x right, y down, z forward) to Voyager's (y up, the object facing +z, the viewer's side), and how
    "up" was chosen.

    Up is the turntable axis when there is one, signed to point up in view 0's image (against the
    camera's +y: a scanner is not mounted upside down); otherwise the camera's -y. The object's base
    (its lowest point along up) goes to y = 0 and the axis (or the middle of its footprint) through
    the origin. ``points`` (N, 3) float64 mm, the model's vertices.
    """
    pts = np.asarray(points, np.float64)
    centre = 0.5 * (pts.min(axis=0) + pts.max(axis=0)) if len(pts) else np.zeros(3)
    if axis and len(axis.get("direction", [])) == 3:
        up = _unit(np.asarray(axis["direction"], np.float64))
        if up[1] > 0:
            up = -up
        through = np.asarray(axis.get("point_mm", centre), np.float64)
        how = "the turntable axis (signed up in view 0's image)"
    else:
        up, through, how = np.array([0.0, -1.0, 0.0]), centre, "view 0's image up (no turntable axis)"
    # Front: from the object towards view 0's camera (at the origin), level with the axis.
    front = -through - np.dot(-through, up) * up
    if np.linalg.norm(front) < 1e-9:
        front = np.array([0.0, 0.0, -1.0]) - np.dot([0.0, 0.0, -1.0], up) * up
    front = _unit(front)
    right = np.cross(up, front)
    R = np.stack([right, up, front])  # rows: Voyager x, y, z in the model's frame
    rotated = pts @ R.T if len(pts) else np.zeros((1, 3))
    a = R @ through
    t = np.array([-a[0], -float(rotated[:, 1].min()), -a[2]])
    return R, t, how


def _quaternion(R: np.ndarray) -> list[float]:
    """(x, y, z, w) of a rotation matrix (Shepperd's method), w >= 0."""
    m = R
    tr = np.trace(m)
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(max(1.0 + m[i, i] - m[j, j] - m[k, k], 1e-300))
        q = [0.0, 0.0, 0.0, (m[k, j] - m[j, k]) / s]
        q[i] = 0.25 * s
        q[j] = (m[j, i] + m[i, j]) / s
        q[k] = (m[k, i] + m[i, k]) / s
    q = np.asarray(q)
    q = q / np.linalg.norm(q)
    if q[3] < 0:
        q = -q
    return [float(round(v, 9)) for v in q]


def _asset(a: SceneAsset) -> list[dict[str, Any]]:
    asset: dict[str, Any] = {"uri": a.uri, "type": "Model", "mimeType": "model/gltf-binary",
                             "byteSize": max(1, a.info.byte_size)}
    if a.info.faces > 0:
        asset["numFaces"] = a.info.faces
    if a.info.image_size > 0:
        asset["imageSize"] = a.info.image_size
    extras = [{"uri": uri, "type": kind, "byteSize": max(1, size)} for uri, kind, size in a.extra]
    return [asset, *extras]


def build_scene(assets: Sequence[SceneAsset], R: np.ndarray, t: np.ndarray, bbox: tuple[np.ndarray, np.ndarray],
                meta: Mapping[str, Any], process: Mapping[str, Any]) -> dict[str, Any]:
    """The SVX document: ``assets`` (one per quality present), the model pose (``R``, ``t`` in mm),
    ``bbox`` (min, max) of the model in its own frame (mm), ``meta`` (title, collection, identifier:
    HTML-escaped, Voyager shows them as HTML) and ``process`` (the paradata, for ``meta.process``)."""
    lo, hi = (np.asarray(b, np.float64) for b in bbox)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    placed = corners @ R.T + t
    plo, phi = placed.min(axis=0), placed.max(axis=0)
    size = float(np.max(phi - plo)) or 1.0
    radius = 0.5 * float(np.linalg.norm(phi - plo)) or 1.0
    target = 0.5 * (plo + phi)
    yfov = 52.0
    dist = radius / math.sin(math.radians(yfov) / 2) * 1.1
    cam_pos = [float(target[0]), float(target[1] + 0.25 * radius), float(target[2] + dist)]
    model = {
        "units": "mm",
        "translation": [float(round(v, 6)) for v in t],
        "rotation": _quaternion(R),
        "boundingBox": {"min": [float(v) for v in lo], "max": [float(v) for v in hi]},
        "derivatives": [{"usage": "Web3D", "quality": a.quality, "assets": _asset(a)} for a in assets],
    }
    light_pos = radius * 2.0
    lights = [
        {"type": "directional", "color": [1.0, 0.95, 0.9], "intensity": 1.0},
        {"type": "directional", "color": [0.9, 0.95, 1.0], "intensity": 0.6},
        {"type": "directional", "color": [0.85, 0.9, 1.0], "intensity": 0.5},
        {"type": "ambient", "color": [1.0, 1.0, 1.0], "intensity": 0.35},
    ]
    # Key from the upper front left, fill from the front right, rim from behind; the lights look at the origin.
    light_nodes = [
        {"name": "Key", "translation": [-light_pos, light_pos, light_pos], "rotation": _look_at([-1, 1, 1]), "light": 0},
        {"name": "Fill", "translation": [light_pos, 0.5 * light_pos, light_pos], "rotation": _look_at([1, 0.5, 1]), "light": 1},
        {"name": "Rim", "translation": [0.0, light_pos, -light_pos], "rotation": _look_at([0, 1, -1]), "light": 2},
        {"name": "Ambient", "light": 3},
    ]  # fmt: skip
    nodes = [
        {"name": "Camera", "translation": cam_pos, "camera": 0},
        {"name": "Lights", "children": [2, 3, 4, 5]},
        *light_nodes,
        {"name": escape(str(meta.get("title") or "Model")), "model": 0, "meta": 0},
    ]
    collection = {k: escape(str(v)) for k, v in meta.items() if v not in (None, "")}
    return {
        "asset": {"type": "application/si-dpo-3d.document+json", "version": SVX_VERSION,
                  "generator": "Graylight", "copyright": str(meta.get("copyright", ""))},
        "scene": 0,
        "scenes": [{"name": escape(str(meta.get("title") or "Scene")), "units": "mm", "nodes": [0, 1, 6], "meta": 0,
                    "setup": 0}],
        "nodes": nodes,
        "cameras": [{"type": "perspective", "perspective": {"yfov": yfov, "znear": max(size / 1000, 0.01),
                                                            "zfar": dist * 20 + size * 10}}],
        "lights": lights,
        "models": [model],
        "metas": [{"collection": collection, "process": dict(process)}],
        "setups": [{
            "units": "mm",
            "interface": {"visible": True, "logo": True, "menu": True, "tools": True},
            "viewer": {"shader": "Default", "exposure": 1, "gamma": 2},
            "navigation": {"type": "Orbit", "enabled": True, "autoZoom": True, "lightsFollowCamera": True,
                           "orbit": {"orbit": [-10, 0, 0], "offset": [float(target[0]), float(target[1]), float(dist)],
                                     "minOrbit": [-90, None, None], "maxOrbit": [90, None, None],
                                     "minOffset": [None, None, 0.1], "maxOffset": [None, None, float(dist * 20)]}},
            "background": {"style": "RadialGradient", "color0": [0.55, 0.57, 0.6], "color1": [0.12, 0.13, 0.15]},
            "floor": {"visible": False, "position": [0, 0, 0], "size": float(size * 4), "color": [0.6, 0.6, 0.6],
                      "opacity": 0.5, "receiveShadow": False},
            "grid": {"visible": False, "color": [0.5, 0.5, 0.5]},
        }],
    }


def _look_at(position: Sequence[float]) -> list[float]:
    """The quaternion turning a light's -z onto the direction from ``position`` to the origin."""
    d = _unit(-np.asarray(position, np.float64))
    z = -d
    x = np.cross([0.0, 1.0, 0.0], z)
    x = _unit(x) if np.linalg.norm(x) > 1e-9 else np.array([1.0, 0.0, 0.0])
    y = np.cross(z, x)
    return _quaternion(np.stack([x, y, z], axis=1))
