"""The published folder of one object (``graylight publish``), written all at once.

From a ``graylight merge`` or ``graylight scan`` output folder::

    DIR/scene.svx.json       Smithsonian Voyager scene (shared.publish.scene)
    DIR/mesh_*.glb           its derivatives, by quality (a scan: cloud_thumb.glb, cloud_high.glb, cloud.ply)
    DIR/qa.json, qa.html     the quality report (shared.publish.qa, shared.publish.qa_html)
    DIR/paradata.json        written by the command's paradata hook once the folder is in place

Everything is written in a hidden staging folder beside DIR and renamed onto it at the end, so a
failure leaves nothing (DIR must not exist or be empty). Titles, collections and identifiers are
kept verbatim in JSON (which escapes them) and escaped in HTML; they never name a file.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from shared.core.errors import InputError
from shared.core.files import atomic_file, write_json_atomic
from shared.publish.glb import GlbInfo, glb_positions, inspect_glb, write_points_glb
from shared.publish.labels import MAX_LABEL_CHARS, check_label
from shared.publish.paradata import load_paradata, sha256_file, software
from shared.publish.qa import QaThresholds, build_qa
from shared.publish.qa_html import coverage_map_png, render_qa_html
from shared.publish.scene import SceneAsset, build_scene, upright_pose
from shared.publish.source import QUALITIES, Source, read_source

log = logging.getLogger(__name__)

__all__ = ["MAX_LABEL_CHARS", "ObjectMeta", "check_label", "publish_folder"]

#: Points in a scan's Thumb level: about 200 kB of GLB (16 bytes a point), Voyager's Thumb budget.
THUMB_POINTS = 12_000


@dataclass(frozen=True)
class ObjectMeta:
    """The object as the museum names it: title, collection, identifier (free text, checked by :func:`check_label`)."""

    title: str
    collection: str = ""
    identifier: str = ""

    def as_dict(self) -> dict[str, str]:
        return {"title": self.title, "collection": self.collection, "identifier": self.identifier}


def _levels(src: Source, stage: Path, points_asset: bool) -> tuple[list[SceneAsset], dict[str, GlbInfo]]:
    """Copy or make the model's levels in ``stage``; measure them. ``points_asset``: copy a cloud-only
    model's PLY beside its GLBs as the High level's ``Points`` asset."""
    assets: list[SceneAsset] = []
    infos: dict[str, GlbInfo] = {}
    if src.levels:
        for q in QUALITIES:
            if q not in src.levels:
                continue
            dst = stage / src.levels[q].name
            shutil.copyfile(src.levels[q], dst)
            info = inspect_glb(dst)
            infos[q] = info
            assets.append(SceneAsset(q, dst.name, info))
        return assets, infos
    from shared.formats.ply import read_ply

    cloud = read_ply(src.cloud)
    xyz = np.asarray(cloud.xyz, np.float64)
    rgb = None if cloud.rgb is None else np.asarray(cloud.rgb, np.uint8)
    if not len(xyz):
        raise InputError(src.cloud, "the cloud has no points: nothing to publish")
    if points_asset:
        shutil.copyfile(src.cloud, stage / src.cloud.name)
    step = max(1, int(np.ceil(len(xyz) / THUMB_POINTS)))
    for q, sl, name in (("Thumb", slice(None, None, step), "cloud_thumb.glb"), ("High", slice(None), "cloud_high.glb")):
        write_points_glb(stage / name, xyz[sl], None if rgb is None else rgb[sl])
        info = inspect_glb(stage / name)
        infos[q] = info
        extra = ((src.cloud.name, "Points", src.cloud.stat().st_size),) if q == "High" and points_asset else ()
        assets.append(SceneAsset(q, name, info, extra))
    return assets, infos


def _process(src: Source, meta: ObjectMeta, thresholds: QaThresholds) -> dict[str, Any]:
    """``meta.process``: the steps that made the model (from the source's paradata), and this publish."""
    agent = software()
    publish = {"stage": "publish", "software": f"Graylight {agent['version']}", "gitRevision": agent.get("gitRevision"),
               "parameters": {"source": str(src.root), **meta.as_dict(), "thresholds": thresholds.__dict__}}
    if src.paradata is None:
        return {"paradata": None, "note": "the source folder has no paradata.json (made before Graylight recorded "
                                          "paradata): its steps are not known beyond its report",
                "steps": [{"stage": src.kind, "method": src.report.get("method"),
                           "seconds": src.report.get("seconds")}, publish]}
    doc = load_paradata(src.paradata)
    acts = sorted((n for n in doc["@graph"] if n.get("@type") == "Activity"), key=lambda a: a.get("startedAtTime", ""))
    agents = {n["@id"]: n for n in doc["@graph"] if n.get("@type") == "SoftwareAgent"}
    steps = []
    for a in acts:
        ag = agents.get(a.get("wasAssociatedWith"), {})
        steps.append({"stage": a.get("stage"), "started": a.get("startedAtTime"), "ended": a.get("endedAtTime"),
                      "software": ag.get("label"), "gitRevision": ag.get("gitRevision"),
                      "libraries": ag.get("libraries"), "host": (a.get("host") or {}).get("name"),
                      "parameters": a.get("parameters"),
                      "inputs": sum(1 for n in doc["@graph"] if n.get("@id") in set(a.get("used", []))),
                      "outputs": sum(1 for n in doc["@graph"] if n.get("wasGeneratedBy") == a.get("@id"))})
    return {"paradata": "paradata.json", "standard": "W3C PROV-O, JSON-LD", "source_paradata_sha256":
            sha256_file(src.paradata), "summary": doc.get("summary", []), "steps": [*steps, publish]}


def publish_folder(source_dir: Path, out: Path, meta: ObjectMeta, thresholds: QaThresholds | None = None,
                   rig: Path | None = None, points_asset: bool = True) -> dict[str, Any]:
    """Publish the merge or scan output ``source_dir`` into ``out`` (see the module's docstring);
    returns the quality report. ``rig``: the rig file, when the source's records name a place it no
    longer is (a job stage's). ``points_asset``: include a cloud-only model's PLY (a job leaves it out:
    the job serves the cloud already). :class:`InputError` for a source that cannot be published or an ``out``
    that holds files."""
    thresholds = thresholds or QaThresholds()
    for field, value in (("--title", meta.title), ("--collection", meta.collection), ("--identifier", meta.identifier)):
        check_label(field, value)
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputError(out, "exists and is not an empty folder (publish into a new one)")
    src = read_source(Path(source_dir))
    out.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        assets, infos = _levels(src, stage, points_asset)
        from shared.formats.ply import read_ply

        cloud_xyz = np.asarray(read_ply(src.cloud).xyz, np.float64)
        top = assets[-1]
        mesh = glb_positions(stage / top.uri) if top.info.faces > 0 else None
        model_pts = mesh if mesh is not None else cloud_xyz
        R, t, how = upright_pose(model_pts, (src.registration or {}).get("turntable_axis"))
        qa, counts = build_qa(src, infos, cloud_xyz, mesh, meta.as_dict(), thresholds, rig)
        qa["pose"] = {"up_from": how, "rotation": R.tolist(), "translation_mm": t.tolist()}
        targets = (mesh if mesh is not None else cloud_xyz) @ R.T + t
        png = coverage_map_png(targets, counts, int(qa["coverage"]["views"]))
        lo, hi = np.min([i.bbox_min for i in infos.values()], axis=0), np.max([i.bbox_max for i in infos.values()], axis=0)
        scene = build_scene(assets, R, t, (lo, hi), meta.as_dict(), _process(src, meta, thresholds))
        write_json_atomic(stage / "scene.svx.json", scene)
        write_json_atomic(stage / "qa.json", qa)
        with atomic_file(stage / "qa.html", suffix=".html") as tmp:
            tmp.write_text(render_qa_html(qa, png), encoding="utf-8")
        os.chmod(stage, 0o755)
        if out.is_dir():
            out.rmdir()
        os.replace(stage, out)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    log.info("published %s: %s", out, qa["verdict"]["line"])
    return json.loads(json.dumps(qa))
