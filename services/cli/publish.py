"""``graylight publish`` and ``graylight rerun``.

* ``publish OUTPUT_DIR|JOB_ID --out DIR [--title T] [--collection C] [--identifier I]``: a museum's
  folder from a ``graylight merge`` or ``graylight scan`` output, or a finished job's (its publish
  stage's files; a job from before that stage is published here from its merge or scan outputs): ``scene.svx.json`` (Smithsonian Voyager) with the
  model's derivatives, ``paradata.json``, ``qa.json`` and ``qa.html`` (:mod:`shared.publish.folder`).
* ``rerun PARADATA.json --out DIR``: repeat the run a paradata document records, from the same inputs
  (checked by sha256 first) with the same parameters, into DIR, and compare every output with the
  recorded one. Exit 0 when every output that is not a timing record is identical, bit for bit.
"""

from __future__ import annotations

import argparse
import hashlib
import logging
import os
import re
import shutil
import sys
from pathlib import Path
from typing import Any

from shared.core.errors import InputError

log = logging.getLogger(__name__)

# Parameters of a calibration that name extra output files; a re-run writes them into DIR too.
_EXTRA_OUTPUTS = ("report", "plot", "export_opencv")


def _cmd_rerun(args: argparse.Namespace) -> int:
    from services.cli.main import build_parser, main
    from services.cli.provenance import RECORDED, argv_for
    from shared.publish.paradata import load_paradata, main_activity
    from shared.publish.rerun import check_inputs, compare_outputs, software_differences

    source = Path(args.paradata)
    doc = load_paradata(source)
    act = main_activity(doc, source)
    stage = act.get("stage")
    if stage not in RECORDED or stage in ("rerun",):
        raise InputError(source, f"stage: {stage!r} is not a command graylight rerun can repeat")
    params = dict(act.get("parameters") or {})
    if not isinstance(params.get("out"), str):
        raise InputError(source, "parameters.out: missing")
    check_inputs(doc, source)
    for line in software_differences(doc):
        log.warning("software differs from the recorded run: %s", line)
    out = Path(args.out).resolve()
    if RECORDED[stage].out_is_dir:
        params["out"] = str(out)
        new_root = out
    else:
        out.mkdir(parents=True, exist_ok=True)
        params["out"] = str(out / Path(params["out"]).name)
        for dest in _EXTRA_OUTPUTS:
            if isinstance(params.get(dest), str):
                params[dest] = str(out / Path(params[dest]).name)
        new_root = out
    if Path(params["out"]).resolve() == Path(str(main_activity(doc).get("parameters", {}).get("out"))).resolve():
        raise InputError("--out", "is where the recorded run wrote: re-run into another folder")
    params.pop("command", None)
    argv = argv_for(build_parser([stage]), stage, params)
    log.info("re-running: graylight %s", " ".join(argv))
    code = main(argv)
    if code != 0:
        return code
    checks = compare_outputs(doc, new_root)
    # A record of timings must match with its timings left out; a record that is not JSON is not compared.
    bad = [c for c in checks if c.status == "missing" or (c.status == "differs" and
                                                          (not c.volatile or c.equal_normalised is False))]
    for c in checks:
        note = {"equal-normalised": " (the same with timings and output paths left out)"}.get(c.status, "")
        if c.status == "differs" and c not in bad:
            note = " (a record of timings: not compared)"
        print(f"{c.status:<16} {c.path}{note}")
    if bad:
        raise InputError(source, f"{len(bad)} of {len(checks)} outputs not reproduced: "
                                 + ", ".join(f"{c.path} {c.status}" for c in bad[:5]))
    same = sum(c.status == "equal" for c in checks)
    print(f"reproduced: {same} of {len(checks)} outputs identical (sha256), "
          f"{sum(c.status == 'equal-normalised' for c in checks)} records equal but for timings")
    return 0


_JOB_ID = re.compile(r"^[0-9a-f]{8}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{12}$")
# Stage folders a job published from, newest first: the publish stage's own, else (a job finished
# before the publish stage existed) the merge's or the triangulation's outputs to publish from here.
_FALLBACK_STAGES = ("mv_merge", "triangulate")


def _download(client: Any, job_id: str, stage: str, files: list[dict[str, Any]], dest: Path) -> None:
    """Every file of one stage of a job into ``dest``, each checked against the listed sha256."""
    for f in files:
        rel = f["name"][len(stage) + 1:]
        target = (dest / rel).resolve()
        if not target.is_relative_to(dest.resolve()):
            raise InputError(f"job {job_id}", f"artifact name {f['name']!r} leaves the folder")
        target.parent.mkdir(parents=True, exist_ok=True)
        data = client._send("GET", f["url"]).content  # noqa: SLF001 (the client's checked request)
        if hashlib.sha256(data).hexdigest() != f["sha256"]:
            raise InputError(f"job {job_id}", f"artifact {f['name']} does not match its sha256")
        target.write_bytes(data)


def fetch_published(client: Any, job_id: str, out: Path, meta: Any, republish: bool = False) -> dict[str, Any]:
    """Write the published folder of a finished job into ``out`` (new or empty): the publish stage's
    files as the service made them (with its paradata.json); with ``republish`` (a title, collection or
    identifier given), or for a job from before that stage, its merge's (or scan's) outputs published
    here. Returns the quality report."""
    import tempfile

    from shared.core.jsonsafe import read_json_bounded
    from shared.publish.folder import publish_folder
    from shared.publish.stages import scan_source

    job = client.job(job_id)
    if job.get("state") != "succeeded":
        raise InputError(f"job {job_id}", f"is {job.get('state')}: only a finished job can be published")
    listing = client.request("GET", f"/v1/jobs/{job_id}/artifacts")["artifacts"]
    by_stage: dict[str, list[dict[str, Any]]] = {}
    for a in listing:
        if "/" in a["name"]:
            by_stage.setdefault(a["stage"], []).append(a)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputError(out, "exists and is not an empty folder (publish into a new one)")
    out.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        if "publish" in by_stage and not republish:
            _download(client, job_id, "publish", by_stage["publish"], work / "pub")
            if out.is_dir():
                out.rmdir()
            os.replace(work / "pub", out)
            return read_json_bounded(out / "qa.json", "qa.json", missing="the job's publish stage wrote no qa.json",
                                     max_bytes=64 << 20)
        stage = next((s for s in _FALLBACK_STAGES if s in by_stage), None)
        if stage is None:
            raise InputError(f"job {job_id}", "has neither a publish stage nor a merge or scan output to publish")
        if "publish" not in by_stage:
            log.warning("job %s has no publish stage (an older job): publishing its %s outputs here", job_id, stage)
        _download(client, job_id, stage, by_stage[stage], work / stage)
        source = work / stage
        if stage == "triangulate":
            source = scan_source(work / stage, Path(f"job {job_id} capture"), Path("rig.json"), work / "scan")
        return publish_folder(source, out, meta)
    finally:
        shutil.rmtree(work, ignore_errors=True)


def _cmd_publish(args: argparse.Namespace) -> int:
    from shared.publish.folder import ObjectMeta, publish_folder

    source = Path(args.source)
    is_job = not source.exists() and _JOB_ID.match(args.source) is not None
    name = args.source if is_job else source.resolve().name
    meta = ObjectMeta(title=args.title if args.title is not None else name, collection=args.collection or "",
                      identifier=args.identifier if args.identifier is not None else name)
    out = Path(args.out)
    if is_job:
        from services.cli.jobs import Client

        named = any(v is not None for v in (args.title, args.collection, args.identifier))
        qa = fetch_published(Client(), args.source, out, meta, republish=named)
    else:
        qa = publish_folder(source, out, meta)
    print(qa["verdict"]["line"])
    levels = ", ".join(f"{d['quality']} {d['file']}" for d in qa["derivatives"])
    print(f"scene:    {out / 'scene.svx.json'} ({levels})")
    print(f"report:   {out / 'qa.html'} ({out / 'qa.json'})")
    print(f"paradata: {out / 'paradata.json'}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("publish", help="a Voyager scene, paradata and quality report from a merge or scan output",
                              description="Write a folder a museum can put on its web server: scene.svx.json "
                                          "(Smithsonian Voyager) with the model's derivatives, paradata.json, "
                                          "qa.json and qa.html, from a graylight merge or scan output folder.")
    p.add_argument("source", help="a graylight merge or scan output folder, or the id of a finished job "
                                  "(GRAYLIGHT_API_URL, GRAYLIGHT_API_KEY)")
    p.add_argument("--out", required=True, help="folder to write (must not exist or be empty)")
    p.add_argument("--title", help="the object's title (default: the source folder's name)")
    p.add_argument("--collection", help="the collection it belongs to")
    p.add_argument("--identifier", help="its identifier in the collection (default: the source folder's name)")
    p.set_defaults(func=_cmd_publish)

    p = subparsers.add_parser("rerun", help="repeat a recorded run from its paradata.json and compare the outputs",
                              description="Repeat the run a paradata.json records, from the same inputs, into "
                                          "another folder; compare every output's sha256 with the recorded one.")
    p.add_argument("paradata", help="paradata.json (or <file>.paradata.json) of the run")
    p.add_argument("--out", required=True, help="folder for the re-made outputs")
    p.set_defaults(func=_cmd_rerun)


__all__ = ["register"]

if __name__ == "__main__":  # pragma: no cover
    from services.cli.main import main

    sys.exit(main())
