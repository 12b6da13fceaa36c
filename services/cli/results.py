"""Commands to open results: ``job show``, ``job download``, ``rerender`` and ``view``.

``graylight job show ID`` prints a job's state, progress, stages, its viewer URL and the links
of its published files; ``graylight job download ID [--artifact NAME]... --out DIR`` fetches its
published files (or the named ones: a short name, ``STAGE/PATH``, or a folder such as
``tiles``), each checked against its SHA-256 and written under a temporary name then renamed.
``graylight rerender ID_OR_BATCH [--batch]`` asks for new previews, rendered beside the
finished jobs. ``graylight view OUTPUT_DIR_OR_JOB`` serves the web viewer and a local
``scan`` / ``merge`` / ``tiles`` output from one origin (no CORS needed) and prints the URL;
given a job id it prints the job service's viewer URL, which serves both already.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import sys
import tempfile
from pathlib import Path
from typing import Any
from urllib.parse import quote

from services.cli.jobs import Client, batch_path, print_links
from shared.core.errors import InputError
from shared.core.files import atomic_file

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("job", help="one job on the job service: show it, download its artifacts")
    js = p.add_subparsers(dest="job_command", required=True)
    c = js.add_parser("show", help="state, progress, stages, the viewer URL and the artifact links")
    c.add_argument("job_id", metavar="ID")
    c.add_argument("--json", action="store_true", help="print the API's JSON")
    c.set_defaults(func=cmd_job_show)
    c = js.add_parser("download", help="fetch a job's published files (checked against their SHA-256)")
    c.add_argument("job_id", metavar="ID")
    c.add_argument("--artifact", action="append", default=None, metavar="NAME",
                   help="a short name (cloud.ply), STAGE/PATH, or a folder (tiles); repeatable; default: every published file")
    c.add_argument("--out", type=Path, required=True, metavar="DIR")
    c.set_defaults(func=cmd_job_download)

    p = sub.add_parser("rerender", help="render a finished job's preview again (or a batch's), beside the job")
    p.add_argument("target", metavar="ID_OR_BATCH")
    p.add_argument("--batch", action="store_true", help="TARGET is a batch (id or name)")
    p.set_defaults(func=cmd_rerender)

    p = sub.add_parser("view", help="open results in the web viewer: a local output folder, or a job")
    p.add_argument("target", metavar="OUTPUT_DIR_OR_JOB")
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=8765)
    p.set_defaults(func=cmd_view)


def _job_path(raw: str) -> str:
    value = raw.strip()
    if not value or "/" in value:
        raise InputError("ID", f"not a job id: {raw!r}")
    return f"/v1/jobs/{quote(value, safe='')}"


def cmd_job_show(args: argparse.Namespace) -> int:
    """Print one job; exit 1 when it failed or was cancelled."""
    client = Client()
    job = client.request("GET", _job_path(args.job_id))
    if args.json:
        print(json.dumps(job, indent=2))
        return 0 if job["state"] not in ("failed", "cancelled") else 1
    print(f"{job['id']}  {job['kind']}  {job['state']}  {job['progress'] * 100:.1f} %  {job['name']}")
    if job.get("error"):
        print(f"  error   {job['error']}")
    for st in job["stages"]:
        secs = f"{st['seconds']:.1f} s" if st.get("seconds") is not None else ""
        print(f"  stage   {st['name']:<18}{st['state']:<10}{st['progress'] * 100:5.1f} %  {secs}")
    rr = job.get("rerender")
    if rr:
        print(f"  rerender {rr['state']} ({rr['reason']}){': ' + rr['error'] if rr.get('error') else ''}")
    print_links(client, job)
    return 0 if job["state"] not in ("failed", "cancelled") else 1


def _wanted(artifacts: list[dict[str, Any]], names: list[str] | None, published: list[str]) -> list[dict[str, Any]]:
    """The artifacts to fetch: the published short names, or those ``names`` select."""
    if not names:
        return [a for a in artifacts if a["name"] in published]
    out = []
    for n in names:
        n = n.strip("/")
        hits = [a for a in artifacts if a["name"] == n or a["name"].startswith(n + "/")]
        if not hits:
            raise InputError("--artifact", f"the job has no artifact {n!r}")
        out.extend(h for h in hits if h not in out)
    return out


def _target(out: Path, name: str) -> Path:
    """``out/name``, refusing a name that would leave ``out``."""
    dest = (out / name).resolve()
    if not dest.is_relative_to(out.resolve()):
        raise InputError(name, "artifact name leaves the output folder")
    return dest


def cmd_job_download(args: argparse.Namespace) -> int:
    """Download artifacts into ``--out``; print each file written."""
    client = Client()
    job = client.request("GET", _job_path(args.job_id))
    listing = client.request("GET", f"{_job_path(args.job_id)}/artifacts")["artifacts"]
    chosen = _wanted(listing, args.artifact, [link["name"] for link in job.get("links", [])])
    if not chosen:
        raise InputError(args.job_id, f"the job ({job['state']}) has published nothing yet")
    args.out.mkdir(parents=True, exist_ok=True)
    for a in chosen:
        dest = _target(args.out, a["name"])
        digest = hashlib.sha256()
        with atomic_file(dest) as tmp, client.http.stream("GET", a["url"]) as r:
            if r.status_code != 200:
                raise InputError(a["name"], f"download failed: HTTP {r.status_code}")
            with open(tmp, "wb") as f:
                for block in r.iter_bytes(1 << 20):
                    digest.update(block)
                    f.write(block)
            if digest.hexdigest() != a["sha256"]:
                raise InputError(a["name"], "downloaded bytes do not match the listed SHA-256")
        print(dest)
    return 0


def cmd_rerender(args: argparse.Namespace) -> int:
    """Ask for new previews; print the ids of the jobs being re-rendered."""
    client = Client()
    if args.batch:
        r = client.request("POST", f"/v1/batches/{batch_path(args.target)}/rerender")
        ids = r["rerendering"]
    else:
        ids = [client.request("POST", f"{_job_path(args.target)}/rerender")["id"]]
    for j in ids:
        print(j)
    return 0


# ---- view -----------------------------------------------------------------------------------
#: Clouds a local output folder may hold, in the order they are looked for.
CLOUD_NAMES = ("merged.ply", "cloud.ply")


def local_results(folder: Path, work: Path) -> dict[str, str]:
    """What the viewer shows of a local output folder, as paths relative to ``folder``
    (``tiles``: a Potree folder; ``mesh``: a glb), building tiles into ``work`` when the folder
    holds only a cloud (a ``scan`` or ``merge`` output without ``graylight tiles``)."""
    out: dict[str, str] = {}
    for cand in (folder, folder / "tiles"):
        if (cand / "metadata.json").is_file():
            out["tiles"] = cand.relative_to(folder).as_posix()
            break
    if (folder / "mesh.glb").is_file():
        out["mesh"] = "mesh.glb"
    if "tiles" not in out:
        cloud = next((folder / n for n in CLOUD_NAMES if (folder / n).is_file()), None)
        if cloud is None:
            raise InputError(folder, "no tiles (metadata.json), mesh.glb or cloud (merged.ply, cloud.ply) to show")
        from shared.render.stages import tiles_stage

        print(f"building tiles of {cloud.name} for the viewer ...", file=sys.stderr)
        tiles_stage(cloud, work / "tiles")
        out["tiles"] = "@work/tiles"
    return out


def view_app(folder: Path, work: Path, shown: dict[str, str], name: str) -> Any:
    """A FastAPI app serving the viewer at ``/`` and ``/viewer/``, the folder at ``/results/``
    and built tiles at ``/work/`` (byte ranges included): one origin, so no CORS."""
    from urllib.parse import urlencode

    from fastapi import FastAPI
    from fastapi.responses import RedirectResponse
    from fastapi.staticfiles import StaticFiles

    from services.viewer.routes import VIEWER_DIST, create_router

    def url(rel: str) -> str:
        return f"/work/{rel[6:]}/" if rel.startswith("@work/") else f"/results/{quote(rel)}".rstrip("/") + "/"

    query = [("tiles", url(shown["tiles"])), ("name", name)]
    if "mesh" in shown:
        query.append(("mesh", f"/results/{quote(shown['mesh'])}"))
    app = FastAPI(title="graylight view", docs_url=None, redoc_url=None, openapi_url=None)

    @app.get("/")
    def page() -> RedirectResponse:
        return RedirectResponse(f"/viewer/?{urlencode(query)}", status_code=307)

    app.include_router(create_router(VIEWER_DIST))
    app.mount("/results", StaticFiles(directory=folder), name="results")
    if work.is_dir():
        app.mount("/work", StaticFiles(directory=work), name="work")
    return app


def cmd_view(args: argparse.Namespace) -> int:
    target = Path(args.target)
    if not target.exists():
        # A job id: the job service serves the viewer and the job's tiles from one origin.
        client = Client()
        job = client.request("GET", _job_path(args.target))
        if not job.get("viewer"):
            raise InputError(args.target, f"the job ({job['state']}) has no tiles to view (yet)")
        print(f"{client.url}{job['viewer']}#key={client.key}")
        return 0
    if not target.is_dir():
        raise InputError(target, "not an output folder (give the folder of a scan, merge or tiles output, or a job id)")
    import uvicorn

    with tempfile.TemporaryDirectory(prefix="graylight-view-") as tmp:
        work = Path(tmp)
        shown = local_results(target.resolve(), work)
        app = view_app(target.resolve(), work, shown, target.resolve().name)
        print(f"http://{args.host}:{args.port}/", flush=True)
        uvicorn.run(app, host=args.host, port=args.port, log_level="warning")
    return 0
