"""Stage adapters: what each stage of :data:`shared.service.jobs.GRAPHS` calls, in the job service.

Each adapter takes a :class:`StageContext` (local folders of the capture and of the
upstream stages' outputs, an empty output folder, the job's parameters) and calls the
plain function in ``shared/`` that the embedded ``graylight scan`` calls too; it returns a
small JSON-able summary. A new stage plugs in by an entry in the graph and one here.

Each adapter imports its stage's science when it first runs (not to dodge a circle: the
layers contract forbids one): a render worker never loads the decoder's kernels.
"""

from __future__ import annotations

import functools
import json
import logging
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from shared.core.errors import InputError, relative_message
from shared.core.files import write_json_atomic
from shared.formats.capture import load_capture
from shared.render.options import PreviewOptions
from shared.service.jobs import base_name
from shared.service.params import check_job_params, compress_options, tiles_options

log = logging.getLogger(__name__)


@dataclass
class StageContext:
    """Everything a stage adapter gets. Paths are local folders; ``out_dir`` is empty and
    becomes the stage's artifact when the adapter returns."""

    job_id: str
    kind: str
    stage: str
    params: dict[str, Any]
    capture_dir: Path | None
    inputs: dict[str, Path]
    out_dir: Path
    progress: Callable[[float], None] = field(default=lambda f: None)
    rig_path: Path | None = None  # a rig uploaded beside the capture, if any
    index: int | None = None  # which instance of a map stage this is


def _jsonable(doc: Any) -> Any:
    """A summary made safe for a JSON column (numpy scalars and paths become plain values)."""
    return json.loads(json.dumps(doc, default=lambda o: o.item() if hasattr(o, "item") else str(o)))


def _rig_for(ctx: StageContext) -> Path:
    if ctx.rig_path is not None:
        return ctx.rig_path
    assert ctx.capture_dir is not None
    capture = load_capture(ctx.capture_dir, check=False)
    if capture.rig is None:
        raise InputError(capture.root / "capture.json", 'no "rig" given: the capture names no rig.json and none was uploaded')
    return capture.rig


def run_ingest(ctx: StageContext) -> dict[str, Any]:
    from shared.scan.pipeline import ingest_stage

    assert ctx.capture_dir is not None
    capture = ingest_stage(ctx.capture_dir, rig=ctx.rig_path)
    # An uploaded rig lives beside the capture, not in it: the summary's "rig" says it was used.
    doc = (replace(capture, rig=None) if ctx.rig_path is not None else capture).to_json()
    write_json_atomic(ctx.out_dir / "capture.json", doc)
    return {
        "projector": [capture.projector_width, capture.projector_height],
        "column_bits": len(capture.columns),
        "row_bits": len(capture.rows),
        "images": len(capture.image_paths()),
        "rig": capture.rig is not None or ctx.rig_path is not None,
    }


def run_decode(ctx: StageContext) -> dict[str, Any]:
    from shared.scan.pipeline import decode_stage

    assert ctx.capture_dir is not None
    return _jsonable(decode_stage(ctx.capture_dir, ctx.out_dir, progress=ctx.progress))


def run_triangulate(ctx: StageContext) -> dict[str, Any]:
    from shared.scan.pipeline import triangulate_stage

    decoded = ctx.inputs["decode"] / "decoded.npz"
    # The capture's white and black frames give the cloud its albedo.
    return _jsonable(triangulate_stage(decoded, _rig_for(ctx), ctx.out_dir, capture_dir=ctx.capture_dir))


def run_tiles_plan(ctx: StageContext) -> dict[str, Any]:
    """Tiles pass 1: bounds and chunks; the summary's ``fanout`` is the number of chunks."""
    from shared.render.octree import plan_tiles

    options = tiles_options(ctx.params.get("tiles"))
    # A scan's cloud, or a multi-view job's merged cloud.
    cloud = ctx.inputs["triangulate"] / "cloud.ply" if "triangulate" in ctx.inputs else ctx.inputs["mv_merge"] / "merged.ply"
    plan = plan_tiles(cloud, ctx.out_dir, **options)
    return {"fanout": len(plan.chunks), "points": plan.points}


def _link(src: Path, dst: Path) -> None:
    # Links (not copies) into a scratch folder; the store skips links when it takes the folder.
    dst.symlink_to(src)


def run_tiles_chunk(ctx: StageContext) -> dict[str, Any]:
    """Tiles pass 2 for chunk ``ctx.index`` (one subtree), independent of every other chunk."""
    from shared.render.octree import PLAN_FILE, build_chunk

    assert ctx.index is not None
    plan_dir = ctx.inputs["tiles_plan"]
    name = f"chunk_{ctx.index:05d}.bin"
    _link(plan_dir / PLAN_FILE, ctx.out_dir / PLAN_FILE)
    _link(plan_dir / name, ctx.out_dir / name)
    build_chunk(ctx.out_dir, ctx.index)
    return {"chunk": ctx.index}


def run_tiles(ctx: StageContext) -> dict[str, Any]:
    """Tiles pass 3: merge every chunk's nodes into the Potree 2.0 folder (the fan-in)."""
    from shared.render.octree import PLAN_FILE, merge_tiles

    work = ctx.out_dir.parent / "merge"
    work.mkdir()
    _link(ctx.inputs["tiles_plan"] / PLAN_FILE, work / PLAN_FILE)
    for name, folder in ctx.inputs.items():
        if base_name(name) == "tiles_chunk":
            for p in folder.glob("chunk_*.nodes.*"):
                _link(p, work / p.name)
    return _jsonable(merge_tiles(work, ctx.out_dir))


def run_preview(ctx: StageContext) -> dict[str, Any]:
    from shared.render.stages import preview_stage

    options = PreviewOptions.from_mapping(ctx.params.get("preview"))
    # A multi-view job's preview: the merge's turntable axis up, its textured derivative when made.
    return _jsonable(preview_stage(ctx.inputs["tiles"], ctx.out_dir / "preview.mp4", options, progress=ctx.progress,
                                   merge_dir=ctx.inputs.get("mv_merge"), derivatives_dir=ctx.inputs.get("derivatives")))


def run_export(ctx: StageContext) -> dict[str, Any]:
    """The cloud (a scan's, or a multi-view job's merged cloud) as LAZ, COPC and E57
    (``cloud.laz``, ``cloud.copc.laz``, ``cloud.e57``)."""
    from shared.render.export import export_cloud

    cloud = ctx.inputs["triangulate"] / "cloud.ply" if "triangulate" in ctx.inputs else ctx.inputs["mv_merge"] / "merged.ply"
    laz = export_cloud(cloud, ctx.out_dir / "cloud.laz", "laz")
    ctx.progress(0.3)
    copc = export_cloud(cloud, ctx.out_dir / "cloud.copc.laz", "copc", workers=1)
    ctx.progress(0.8)
    e57 = export_cloud(cloud, ctx.out_dir / "cloud.e57", "e57")
    return _jsonable({"points": laz["points"], "scale": laz["scale"], "laz_bytes": laz["bytes"],
                      "copc_bytes": copc["bytes"], "copc_nodes": copc["nodes"], "e57_bytes": e57["bytes"]})  # fmt: skip


def run_compress(ctx: StageContext) -> dict[str, Any]:
    """The range image as ``range.glr`` (and ``compress.json``); a copy of the raw ``range.npz``
    too unless ``params.compress.keep_range`` is false. The raw image is triangulate's detached
    file (the runner lays it in ``ctx.inputs["triangulate"]``); with keep_range false the runner
    deletes it once this output is stored (``StageSpec.release_unless``)."""
    from shared.compress.files import compress_file

    options = compress_options(ctx.params.get("compress"))
    raw = ctx.inputs["triangulate"] / "range.npz"
    summary = compress_file(raw, ctx.out_dir / "range.glr", quantum=options.get("quantum"), max_error=options.get("max_error"))
    summary["kept_range"] = bool(options.get("keep_range", True))
    if summary["kept_range"]:
        shutil.copyfile(raw, ctx.out_dir / "range.npz")  # a link would not be stored with the output
    summary["input"], summary["output"] = "range.npz", "range.glr"
    write_json_atomic(ctx.out_dir / "compress.json", summary)
    return _jsonable(summary)


def run_mv_plan(ctx: StageContext) -> dict[str, Any]:
    """Validate a scan set (every view readable, sizes and rigs consistent); fan out one task per view."""
    from shared.formats.scanset import load_scanset

    assert ctx.capture_dir is not None
    ss = load_scanset(ctx.capture_dir)
    shutil.copyfile(ss.path, ctx.out_dir / "scanset.json")
    return {"fanout": len(ss.views), "views": [{"name": v.name, "kind": v.kind} for v in ss.views]}


def _view_spec(ctx: StageContext) -> Any:
    """The scan set's view that this instance of a per-view stage works on."""
    from shared.formats.scanset import load_scanset

    assert ctx.capture_dir is not None and ctx.index is not None
    return load_scanset(ctx.capture_dir).views[ctx.index]


def _in_view(spec: Any, step: Callable[[], dict[str, Any]]) -> dict[str, Any]:
    """Run ``step``; an input error names the view (``views[2] (view_02): ...``)."""
    try:
        return step()
    except InputError as exc:  # its file named as in the scan set, not where this worker unpacked it
        raise InputError(spec.where, relative_message(exc, spec.path.parent)) from None


def run_mv_ingest(ctx: StageContext) -> dict[str, Any]:
    """Check one view of a scan set completely without decoding: a capture's images and rig (as
    the scan's ingest does), or a cloud view's PLY (the merge reads it from the set)."""
    from shared.merge.views import load_view
    from shared.scan.pipeline import ingest_stage

    spec = _view_spec(ctx)
    if spec.kind == "cloud":
        return {"view": spec.name, "kind": "cloud", "points": len(load_view(spec))}

    def ingest() -> dict[str, Any]:
        capture = ingest_stage(spec.path, spec.rig)
        if capture.rig is None:
            raise InputError(spec.path / "capture.json", "no rig")
        return {"view": spec.name, "kind": "capture", "images": len(capture.image_paths()),
                "projector": [capture.projector_width, capture.projector_height]}

    return _in_view(spec, ingest)


def run_mv_decode(ctx: StageContext) -> dict[str, Any]:
    """Decode one captured view (``decoded.npz``); nothing to do for a cloud view."""
    from shared.scan.pipeline import decode_stage

    spec = _view_spec(ctx)
    if spec.kind == "cloud":
        return {"view": spec.name, "kind": "cloud"}
    summary = _in_view(spec, lambda: decode_stage(spec.path, ctx.out_dir, progress=ctx.progress))
    return _jsonable({**summary, "view": spec.name, "kind": "capture"})


def run_mv_triangulate(ctx: StageContext) -> dict[str, Any]:
    """Triangulate one decoded view with its rig (``cloud.ply``, ``range.npz``: the raw range
    image the merge keeps); nothing to do for a cloud view."""
    from shared.scan.pipeline import triangulate_stage

    spec = _view_spec(ctx)
    if spec.kind == "cloud":
        return {"view": spec.name, "kind": "cloud"}
    decoded = ctx.inputs[f"mv_decode#{ctx.index}"] / "decoded.npz"
    summary = _in_view(spec, lambda: triangulate_stage(decoded, spec.rig, ctx.out_dir, capture_dir=spec.path))
    return _jsonable({**summary, "view": spec.name, "kind": "capture"})


def run_mv_merge(ctx: StageContext) -> dict[str, Any]:
    """Register, fuse and mesh the views (:func:`shared.merge.pipeline.merge_views`)."""
    from shared.formats.scanset import load_scanset
    from shared.merge.pipeline import merge_views
    from shared.merge.views import load_view, view_from_scan_outputs

    assert ctx.capture_dir is not None
    ss = load_scanset(ctx.capture_dir)
    views = [view_from_scan_outputs(v, ctx.inputs[f"mv_triangulate#{i}"], ctx.inputs[f"mv_decode#{i}"])
             if v.kind == "capture" else load_view(v) for i, v in enumerate(ss.views)]  # fmt: skip
    report = merge_views(views, ss, ctx.out_dir, drop_unregistered=bool(ctx.params.get("drop_unregistered", False)),
                         progress=ctx.progress)
    return _jsonable({"views": report["views"], "registered_views": report["registered_views"],
                      "dropped_views": report["dropped_views"], "points": report["points"]["merged"],
                      "faces": report["mesh"]["faces"], "loop_closure": report["registration"]["loop_closure"]})


def run_mv_compress(ctx: StageContext) -> dict[str, Any]:
    """The merged object compressed at ``params.compress`` (default lossless at 0.02 mm): the
    merged cloud as ``merged.glo`` and each view's range image as ``ranges/<view>.glr``; only the
    smaller of the two is kept (the views' when they are smaller, else the cloud)."""
    from shared.compress.files import compress_file

    options = compress_options(ctx.params.get("compress"))
    mode = {k: options[k] for k in ("quantum", "max_error") if k in options}
    merged = ctx.inputs["mv_merge"]
    cloud = compress_file(merged / "merged.ply", ctx.out_dir / "merged.glo", **mode)
    views = []
    for raw in sorted((merged / "ranges").glob("*.npz")) if (merged / "ranges").is_dir() else []:
        views.append(compress_file(raw, ctx.out_dir / "ranges" / f"{raw.stem}.glr", **mode))
    views_bytes = sum(v["bytes"] for v in views)
    kept = "views" if views and views_bytes < cloud["bytes"] else "merged"
    if kept == "views":
        (ctx.out_dir / "merged.glo").unlink()
    elif views:
        shutil.rmtree(ctx.out_dir / "ranges")
    summary = {"kept": kept, "merged_bytes": cloud["bytes"], "merged_points": cloud["count"],
               "views_bytes": views_bytes, "views": len(views), "mode": cloud["mode"],
               "quantum": cloud["quantum"], "max_error": cloud["max_error"]}
    write_json_atomic(ctx.out_dir / "compress.json", summary)
    return _jsonable(summary)


def run_derivatives(ctx: StageContext) -> dict[str, Any]:
    """The textured web derivatives of the merge (:func:`shared.derive.pipeline.make_derivatives`):
    ``mesh_<level>.glb`` per level of ``params.derivatives.levels`` (Voyager's by default)."""
    from shared.derive.pipeline import make_derivatives

    options = ctx.params.get("derivatives")
    options = options if isinstance(options, dict) else {}
    report = make_derivatives(ctx.inputs["mv_merge"], ctx.out_dir, levels=options.get("levels"),
                              colour=options.get("colour", "photo"), scanset=ctx.capture_dir)
    return _jsonable({"colour": report["colour_baked"], "warnings": report["warnings"],
                      "levels": [{k: lv[k] for k in ("level", "file", "faces", "texture_px", "bytes")}
                                 for lv in report["levels"]]})


def run_calibrate(ctx: StageContext) -> dict[str, Any]:
    from shared.calib.session import calibrate_session

    assert ctx.capture_dir is not None
    return _jsonable(
        calibrate_session(ctx.capture_dir, ctx.out_dir, progress=lambda done, total, _msg: ctx.progress(done / max(total, 1)))
    )


def run_probe(ctx: StageContext) -> dict[str, Any]:
    """The self-test stage: sleep ``params.seconds`` (reporting progress), write probe.json."""
    seconds = float(check_job_params("probe", {"seconds": ctx.params.get("seconds", 0.0)})["seconds"])
    start = time.time()
    end = start + float(seconds)
    while (now := time.time()) < end:
        ctx.progress((now - start) / max(float(seconds), 1e-9))
        time.sleep(min(0.05, end - now))
    doc = {"job": ctx.job_id, "seconds": seconds, "started": start, "finished": time.time()}
    write_json_atomic(ctx.out_dir / "probe.json", doc)
    return doc


def run_publish(ctx: StageContext) -> dict[str, Any]:
    """The object as a museum publishes it (:func:`shared.publish.folder.publish_folder`): the Voyager
    scene with its derivatives, qa.json and qa.html, from the merge (multiview) or the triangulated
    cloud (scan); the job's paradata.json is written by :func:`_recorded`."""
    import tempfile

    from shared.publish.folder import ObjectMeta, publish_folder
    from shared.publish.stages import merge_source, scan_source

    assert ctx.capture_dir is not None
    meta = ObjectMeta(title=str(ctx.params.get("title") or f"Job {ctx.job_id}"),
                      collection=str(ctx.params.get("collection") or ""),
                      identifier=str(ctx.params.get("identifier") or ctx.job_id))
    if ctx.kind == "multiview":
        from shared.formats.scanset import load_scanset

        rig = load_scanset(ctx.capture_dir).rig
        with tempfile.TemporaryDirectory(prefix="publish-src-") as work:
            # The derivatives stage's textured levels when the job made them, else the merge's LODs.
            source = merge_source(ctx.inputs["mv_merge"], ctx.inputs.get("derivatives"), Path(work) / "merge")
            qa = publish_folder(source, ctx.out_dir, meta, rig=rig, points_asset=False)
    else:
        with tempfile.TemporaryDirectory(prefix="publish-src-") as work:
            rig = _rig_for(ctx)
            source = scan_source(ctx.inputs["triangulate"], ctx.capture_dir, rig, Path(work) / "scan")
            qa = publish_folder(source, ctx.out_dir, meta, rig=rig, points_asset=False)
    return {"verdict": qa["verdict"]["line"], "publishable": qa["verdict"]["publishable"],
            "derivatives": [d["file"] for d in qa["derivatives"]]}


#: Stages whose record is their job's paradata.json (served): the last stage of each graph that has one.
PUBLIC_PARADATA_STAGES = frozenset({"publish", "calibrate"})


def _recorded(func: Callable[[StageContext], dict[str, Any]]) -> Callable[[StageContext], dict[str, Any]]:
    """The adapter, leaving the stage's paradata in its output (shared.publish.stages.record_stage):
    ``.paradata.json``, or the job's ``paradata.json`` for :data:`PUBLIC_PARADATA_STAGES`."""

    @functools.wraps(func)
    def run(ctx: StageContext) -> dict[str, Any]:
        from shared.publish.stages import record_stage

        started = datetime.now(UTC)
        summary = func(ctx)
        record_stage(stage=ctx.stage, job_id=ctx.job_id, kind=ctx.kind, params=ctx.params,
                     capture_dir=ctx.capture_dir, inputs=ctx.inputs, out_dir=ctx.out_dir, started=started,
                     ended=datetime.now(UTC), public=base_name(ctx.stage) in PUBLIC_PARADATA_STAGES)
        return summary

    return run


STAGE_FUNCS: dict[str, Callable[[StageContext], dict[str, Any]]] = {
    "ingest": run_ingest,
    "decode": run_decode,
    "triangulate": run_triangulate,
    "tiles_plan": run_tiles_plan,
    "tiles_chunk": run_tiles_chunk,
    "tiles": run_tiles,
    "preview": run_preview,
    "export": run_export,
    "compress": run_compress,
    "mv_compress": run_mv_compress,
    "calibrate": run_calibrate,
    "probe": run_probe,
    "mv_plan": run_mv_plan,
    "mv_ingest": run_mv_ingest,
    "mv_decode": run_mv_decode,
    "mv_triangulate": run_mv_triangulate,
    "mv_merge": run_mv_merge,
    "derivatives": run_derivatives,
    "publish": run_publish,
}
STAGE_FUNCS = {name: _recorded(func) for name, func in STAGE_FUNCS.items()}
