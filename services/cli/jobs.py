"""Job-service commands: ``serve``, ``worker``, ``beat``, ``submit``, ``jobs`` and ``keys``.

``graylight serve [--host H] [--port P]`` runs the API; ``graylight worker [--queues
cpu,render] [--concurrency N]`` a Celery worker (the ``control`` queue, where the
reconciler runs, is added unless ``--no-control``); ``graylight beat`` the one beat
scheduler. ``graylight submit CAPTURE_DIR_OR_ARCHIVE... [--wait] [--batch NAME]`` sends
captures, scan sets and calibration sessions (the kind detected from the folder or archive) to
``GRAYLIGHT_API_URL`` with ``GRAYLIGHT_API_KEY`` and prints one job id per line (the batch's id
on stderr); ``--wait`` follows them with a progress bar (on stderr), then prints each job's
viewer and artifact links, and exits 1 if any failed.
``graylight keys create NAME`` prints a new API key (stored hashed in the job database).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from shared.core.errors import GraylightError, InputError
from shared.service.config import get_settings
from shared.service.jobs import GRAPHS, QUEUES, ROOT_FILES

log = logging.getLogger(__name__)

#: Archives larger than this go through a resumable upload session instead of one request.
SESSION_THRESHOLD = 32 << 20
CHUNK = 16 << 20
TERMINAL = ("succeeded", "failed", "cancelled")


class ServiceError(GraylightError):
    """The API answered with an error, or could not be reached."""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("serve", help="run the HTTP API")
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=8000)
    p.set_defaults(func=cmd_serve)

    p = sub.add_parser("worker", help="run a Celery worker for the job service")
    p.add_argument("--queues", default="cpu,render", help="comma-separated logical queues (cpu, render)")
    p.add_argument("--concurrency", type=int, default=None, help="worker processes (default: CPU count)")
    p.add_argument("--no-control", action="store_true", help="do not also consume the control queue (reconciler)")
    p.add_argument("--loglevel", default="INFO")
    p.set_defaults(func=cmd_worker)

    p = sub.add_parser("beat", help="run the beat scheduler (reconciler, nightly re-render); run exactly one")
    p.add_argument("--loglevel", default="INFO")
    p.set_defaults(func=cmd_beat)

    p = sub.add_parser("submit", help="submit captures (folders or zip/tar archives) to the job service")
    p.add_argument("captures", nargs="+", metavar="CAPTURE_DIR_OR_ARCHIVE")
    p.add_argument("--wait", action="store_true", help="follow the jobs; exit 1 if any failed")
    p.add_argument("--batch", default=None, metavar="NAME", help="put the jobs in this batch (its id is printed on stderr)")
    p.add_argument("--kind", default=None, choices=sorted(GRAPHS),
                   help="job kind: scan (a capture), multiview (a scan set), calibrate (a board session), probe "
                        "(a self-test); default: detected, scanset.json at the top is a scan set, board.json a "
                        "calibration session, anything else a capture")  # fmt: skip
    p.add_argument("--rig", type=Path, default=None, help="rig.json to use instead of the capture's")
    p.add_argument("--params", default=None, metavar="JSON",
                   help='job parameters, e.g. \'{"render": false}\' or \'{"preview": {"seconds": 5}}\'')
    p.add_argument("--timeout", type=float, default=None, help="with --wait: give up after this many seconds")
    p.set_defaults(func=cmd_submit)

    p = sub.add_parser("jobs", help="list your jobs on the job service")
    p.add_argument("--state", default=None, choices=["queued", "running", "succeeded", "failed", "cancelled"])
    p.add_argument("--batch", default=None, metavar="ID_OR_NAME", help="only this batch's jobs")
    p.add_argument("--limit", type=int, default=50, help="jobs a page (newest first)")
    p.add_argument("--offset", type=int, default=0, help="skip this many (the next page: the offset printed)")
    p.add_argument("--json", action="store_true", help="print the API's JSON")
    p.set_defaults(func=cmd_jobs)

    p = sub.add_parser("batch", help="follow a batch on the job service: status, report, retry-failed")
    bs = p.add_subparsers(dest="batch_command", required=True)
    c = bs.add_parser("status", help="job counts by state, rejected files and progress")
    c.add_argument("batch_id", metavar="ID_OR_NAME")
    c.set_defaults(func=cmd_batch_status)
    c = bs.add_parser("report", help="one row per capture: name, state, points, failure reason, artifact links")
    c.add_argument("batch_id", metavar="ID_OR_NAME")
    c.add_argument("--format", choices=["csv", "json"], default="csv")
    c.add_argument("--out", type=Path, default=None, help="write the report here (default: standard output)")
    c.set_defaults(func=cmd_batch_report)
    c = bs.add_parser("retry-failed", help="re-run the failed and cancelled jobs (only what failed)")
    c.add_argument("batch_id", metavar="ID_OR_NAME")
    c.set_defaults(func=cmd_batch_retry)

    p = sub.add_parser("keys", help="manage API keys (in the job database)")
    ks = p.add_subparsers(dest="keys_command", required=True)
    c = ks.add_parser("create", help="create a key and print it (shown once)")
    c.add_argument("name")
    c.set_defaults(func=cmd_keys_create)
    c = ks.add_parser("list", help="list keys (name, prefix)")
    c.set_defaults(func=cmd_keys_list)
    c = ks.add_parser("revoke", help="revoke the key with this prefix")
    c.add_argument("prefix")
    c.set_defaults(func=cmd_keys_revoke)


# ---- service processes ----------------------------------------------------------------------
def cmd_serve(args: argparse.Namespace) -> int:
    import uvicorn

    from services.api.app import create_app
    from shared.service.logs import configure_logging

    settings = get_settings()
    configure_logging(settings, logging.INFO)
    # With JSON logs uvicorn keeps its hands off logging: its records reach the root's JSON handler.
    log_config = None if settings.log_format == "json" else uvicorn.config.LOGGING_CONFIG
    uvicorn.run(create_app(settings), host=args.host, port=args.port, log_level="info", timeout_graceful_shutdown=10,
                log_config=log_config)  # fmt: skip
    return 0


def cmd_worker(args: argparse.Namespace) -> int:
    from shared.service.logs import configure_logging
    from workers.celery_app import get_app

    settings = get_settings()
    configure_logging(settings, args.loglevel.upper())
    logical = [q.strip() for q in args.queues.split(",") if q.strip()]
    for q in logical:
        if q not in QUEUES:
            raise InputError("--queues", f"unknown queue {q!r} ({', '.join(QUEUES)})")
    if not args.no_control and "control" not in logical:
        logical.append("control")
    argv = [
        "worker",
        "-Q", ",".join(settings.queue(q) for q in logical),
        "-l", args.loglevel,
        "-n", f"graylight-{os.getpid()}@%h",
        "--without-gossip", "--without-mingle", "--without-heartbeat",
    ]  # fmt: skip
    if args.concurrency:
        argv += ["-c", str(args.concurrency)]
    get_app(settings).worker_main(argv)
    return 0


def cmd_beat(args: argparse.Namespace) -> int:
    from shared.service.logs import configure_logging
    from workers.beat import run_beat

    settings = get_settings()
    configure_logging(settings, args.loglevel.upper())
    run_beat(settings, args.loglevel)
    return 0


# ---- keys -------------------------------------------------------------------------------------
def cmd_keys_create(args: argparse.Namespace) -> int:
    from shared.service.jobstore import JobStore

    name = args.name.strip()
    if not name or len(name) > 200:
        raise InputError("NAME", "a key name must be 1-200 characters")
    _rec, secret = JobStore(get_settings().database_url).create_key(name)
    print(secret)
    return 0


def cmd_keys_list(args: argparse.Namespace) -> int:
    from shared.service.jobstore import JobStore

    for k in JobStore(get_settings().database_url).list_keys():
        print(f"{k.prefix}\t{k.name}\t{time.strftime('%Y-%m-%d %H:%M', time.gmtime(k.created_at))}")
    return 0


def cmd_keys_revoke(args: argparse.Namespace) -> int:
    from shared.service.jobstore import JobStore

    if not JobStore(get_settings().database_url).revoke_key(args.prefix):
        raise InputError(args.prefix, "no key with this prefix")
    return 0


# ---- the client -------------------------------------------------------------------------------
class Client:
    """A small client of the job-service API (``GRAYLIGHT_API_URL``, ``GRAYLIGHT_API_KEY``)."""

    def __init__(self, url: str | None = None, key: str | None = None, timeout: float = 120.0, http: Any = None) -> None:
        import httpx

        settings = get_settings()
        self.url = (url or settings.api_url).rstrip("/")
        key = key or settings.api_key
        if not key:
            raise InputError("GRAYLIGHT_API_KEY", "not set (create one with `graylight keys create NAME`)")
        # ``http``: any httpx.Client-like object (tests pass the API's TestClient).
        self.http = http or httpx.Client(base_url=self.url, timeout=timeout)
        self.http.headers["Authorization"] = f"Bearer {key}"
        self.key = key

    def _send(self, method: str, path: str, **kw: Any) -> Any:
        """The ``httpx`` response of a request; :class:`ServiceError` when it fails or answers >= 400."""
        import httpx

        try:
            r = self.http.request(method, path, **kw)
        except httpx.HTTPError as exc:
            raise ServiceError(f"{self.url}{path}: {exc}") from None
        if r.status_code >= 400:
            try:
                detail = error_text(r.json().get("detail"))
            except ValueError:
                detail = r.text[:300]
            raise ServiceError(f"{method} {path}: HTTP {r.status_code}: {detail}")
        return r

    def request(self, method: str, path: str, **kw: Any) -> Any:
        r = self._send(method, path, **kw)
        return r.json() if r.content else None

    def submit_archive(self, archive: Path, label: str, kind: str = "scan", batch: str | None = None,
                       rig: Path | None = None, params: dict[str, Any] | None = None,
                       session_threshold: int = SESSION_THRESHOLD, chunk: int = CHUNK) -> dict[str, Any]:  # fmt: skip
        """Submit one archive: in one multipart request, or by a resumable upload session when
        larger than ``session_threshold`` bytes."""
        data: dict[str, str] = {"kind": kind, "name": label}
        if batch:
            data["batch"] = batch
        if params:
            data["params"] = json.dumps(params)
        if archive.stat().st_size <= session_threshold or rig is not None:
            files: dict[str, Any] = {"capture": (label, open(archive, "rb"), "application/octet-stream")}
            if rig is not None:
                files["rig"] = ("rig.json", rig.read_bytes(), "application/json")
            try:
                return self.request("POST", "/v1/jobs", data=data, files=files)
            finally:
                files["capture"][1].close()
        upload = self.upload(archive, label, chunk=chunk)
        body: dict[str, Any] = {"kind": kind, "name": label, "upload_id": upload, "params": params or {}}
        if batch:
            body["batch"] = batch
        return self.request("POST", "/v1/jobs", json=body)

    def upload(self, archive: Path, label: str, chunk: int = CHUNK, attempts: int = 6, resume: str | None = None) -> str:
        """Send ``archive`` through an upload session, resuming after a failed chunk; its id.
        ``resume`` continues an earlier session from the offset the server reports."""
        if resume:
            up = self.request("GET", f"/v1/uploads/{resume}")
        else:
            up = self.request("POST", "/v1/uploads", json={"filename": label})
        size = archive.stat().st_size
        offset = int(up["offset"])
        failures = 0
        with open(archive, "rb") as f:
            while offset < size:
                f.seek(offset)
                block = f.read(chunk)
                try:
                    r = self.request("PATCH", f"/v1/uploads/{up['id']}", content=block,
                                     headers={"Upload-Offset": str(offset), "Content-Type": "application/octet-stream"})  # fmt: skip
                    offset = int(r["offset"])
                    failures = 0
                except ServiceError as exc:
                    failures += 1
                    if failures >= attempts:
                        raise
                    log.warning("upload chunk at %d failed (%s); resuming", offset, exc)
                    time.sleep(min(2.0**failures * 0.2, 5.0))
                    offset = int(self.request("GET", f"/v1/uploads/{up['id']}")["offset"])
        return str(up["id"])

    def job(self, job_id: str) -> dict[str, Any]:
        return self.request("GET", f"/v1/jobs/{job_id}")

    def text(self, path: str) -> str:
        """The body of ``GET path`` as text (a CSV report); :class:`ServiceError` on an error."""
        return self._send("GET", path).text


def error_text(detail: Any) -> str:
    """One line of an API error's ``detail``: the text itself, or a 422's list of
    ``{"loc", "msg"}`` as ``FIELD: MESSAGE; ...`` (the location without its ``body``/``query``)."""
    if not isinstance(detail, list):
        return str(detail)
    parts = []
    for item in detail:
        loc = [str(p) for p in (item.get("loc") or [])[1:]] if isinstance(item, dict) else []
        msg = item.get("msg", item) if isinstance(item, dict) else item
        parts.append(f"{'.'.join(loc)}: {msg}" if loc else str(msg))
    return "; ".join(parts)


def _as_archive(path: Path, tmp: Path) -> Path:
    from shared.service.archive import pack_folder

    if path.is_dir():
        return pack_folder(path, tmp / f"{path.name or 'capture'}.zip")
    if path.is_file():
        return path
    raise InputError(path, "no such capture folder or archive")


def cmd_submit(args: argparse.Namespace) -> int:
    params = None
    if args.params:
        try:
            params = json.loads(args.params)
        except json.JSONDecodeError as exc:
            raise InputError("--params", f"not JSON ({exc.msg})") from None
        if not isinstance(params, dict):
            raise InputError("--params", "must be a JSON object")
    client = Client()
    ids: list[str] = []
    batch_shown = False
    with tempfile.TemporaryDirectory(prefix="graylight-submit-") as tmp:
        for raw in args.captures:
            path = Path(raw)
            kind = args.kind or detect_kind(path)
            archive = _as_archive(path, Path(tmp))
            label = path.name if path.is_dir() else archive.name
            job = client.submit_archive(archive, label, kind=kind, batch=args.batch, rig=args.rig, params=params)
            print(job["id"], flush=True)
            if job.get("batch") and not batch_shown:
                # stdout stays one job id a line (scripts read it); the batch id goes to stderr.
                print(f"batch {job['batch']} ({args.batch})", file=sys.stderr, flush=True)
                batch_shown = True
            ids.append(job["id"])
            if archive.parent == Path(tmp):
                archive.unlink()
    if not args.wait:
        return 0
    status = follow(client, ids, timeout=args.timeout)
    for j in ids:
        print_links(client, client.job(j))
    return status


def print_links(client: Client, job: dict[str, Any], out: Any = None) -> None:
    """Print a job's viewer URL (with the key in its fragment, which browsers never send) and
    the absolute URLs of its published files."""
    out = out or sys.stdout
    print(f"{job['id']}  {job['state']}  {job.get('name', '')}", file=out)
    if job.get("viewer"):
        print(f"  viewer  {client.url}{job['viewer']}#key={client.key}", file=out)
    for link in job.get("links", []):
        print(f"  {link['name']:<16}{client.url}{link['url']}", file=out)


def detect_kind(path: Path) -> str:
    """The job kind of a folder or archive, from the file at its top (or in its one top
    folder): ``scanset.json`` a multiview job, ``board.json`` a calibration, else a scan."""
    names: list[str] = []
    if path.is_dir():
        names = [p.name for p in path.iterdir()]
    elif path.is_file():
        names = _top_names(path)
    by_file = {f: k for k, f in ROOT_FILES.items()}
    for marker in ("scanset.json", "board.json"):
        if marker in names:
            return by_file[marker]
    return "scan"


def _top_names(archive: Path) -> list[str]:
    """Names at the top of a zip or tar archive, or inside its single top folder ([] when it
    is neither: the service names the problem)."""
    import tarfile
    import zipfile

    try:
        if zipfile.is_zipfile(archive):
            with zipfile.ZipFile(archive) as z:
                members = z.namelist()
        elif tarfile.is_tarfile(archive):
            with tarfile.open(archive) as t:
                members = t.getnames()
        else:
            return []
    except (OSError, zipfile.BadZipFile, tarfile.TarError):
        return []
    parts = [m.strip("/").split("/") for m in members if m.strip("/") and not m.startswith("__MACOSX")]
    tops = sorted({p[0] for p in parts})
    if len(tops) == 1:  # one folder zipped whole: look inside it
        return tops + sorted({p[1] for p in parts if len(p) > 1})
    return tops


def follow(client: Client, ids: list[str], timeout: float | None = None, interval: float = 0.5) -> int:
    """Follow jobs with a progress bar on stderr until each is final; 1 if any did not succeed."""
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    console = Console(stderr=True)
    states: dict[str, dict[str, Any]] = {}
    deadline = None if timeout is None else time.monotonic() + timeout
    with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.percentage:>3.0f}%"),
                  TimeElapsedColumn(), console=console, transient=False) as bar:  # fmt: skip
        many = len(ids) > 8
        tasks = {j: bar.add_task(j[:8], total=1.0) for j in ([] if many else ids)}
        overall = bar.add_task(f"{len(ids)} jobs", total=float(len(ids))) if many else None
        while True:
            for j in ids:
                if states.get(j, {}).get("state") in TERMINAL:
                    continue
                try:
                    states[j] = client.job(j)
                except ServiceError as exc:
                    log.warning("%s", exc)
            done = [j for j in ids if states.get(j, {}).get("state") in TERMINAL]
            for j, t in tasks.items():
                s = states.get(j, {})
                running = next((st["name"] for st in s.get("stages", []) if st["state"] == "running"), "")
                bar.update(t, completed=float(s.get("progress", 0.0)),
                           description=f"{j[:8]} {s.get('state', '?')} {running}".rstrip())  # fmt: skip
            if overall is not None:
                bar.update(overall, completed=len(done) + sum(float(states.get(j, {}).get("progress", 0)) for j in ids if j not in done))
            if len(done) == len(ids):
                break
            if deadline is not None and time.monotonic() > deadline:
                console.print(f"gave up waiting after {timeout:g} s")
                return 1
            time.sleep(interval)
    bad = [j for j in ids if states[j]["state"] != "succeeded"]
    for j in bad:
        console.print(f"{j} {states[j]['state']}: {states[j].get('error') or ''}")
    return 1 if bad else 0


def cmd_jobs(args: argparse.Namespace) -> int:
    client = Client()
    params: dict[str, Any] = {"limit": args.limit, "offset": args.offset}
    if args.state:
        params["state"] = args.state
    if args.batch:
        params["batch"] = args.batch
    page = client.request("GET", "/v1/jobs", params=params)
    if args.json:
        print(json.dumps(page, indent=2))
        return 0
    for j in page["jobs"]:
        created = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(j["created_at"]))
        line = f"{j['id']}  {j['state']:<9}  {j['progress'] * 100:5.1f}%  {created}  {j['name']}"
        if j.get("error"):
            line += f"  [{j['error']}]"
        print(line)
    if page["total"] > len(page["jobs"]):
        more = f"; next page: --offset {page['next_offset']}" if page.get("next_offset") is not None else ""
        print(f"({len(page['jobs'])} of {page['total']} from {args.offset}{more})", file=sys.stderr)
    return 0


# ---- batches ----------------------------------------------------------------------------------
def batch_path(raw: str) -> str:
    """A batch's id or name, percent-encoded for its URL path."""
    from urllib.parse import quote

    value = raw.strip()
    if not value or "/" in value:
        raise InputError("ID", f"not a batch id or name: {raw!r}")
    return quote(value, safe="")


def cmd_batch_status(args: argparse.Namespace) -> int:
    """Print a batch's counts by state and its progress; exit 1 when any job failed."""
    b = Client().request("GET", f"/v1/batches/{batch_path(args.batch_id)}")
    counts = ", ".join(f"{n} {s}" for s, n in sorted(b["counts"].items())) or "no jobs"
    print(f"{b['id']}  {b['name']}: {b['total']} captures, {counts}, {b['progress'] * 100:.1f} % done")
    for r in b.get("rejected", []):
        print(f"  rejected  {r['capture']}: {r['error']}")
    return 1 if b["counts"].get("failed") or b["counts"].get("rejected") else 0


def cmd_batch_report(args: argparse.Namespace) -> int:
    """Write a batch's report (CSV or JSON) to ``--out`` (atomically) or standard output."""
    from shared.core.files import atomic_file

    client = Client()
    path = f"/v1/batches/{batch_path(args.batch_id)}/report.{args.format}"
    if args.format == "csv":
        text = client.text(path)
    else:
        text = json.dumps(client.request("GET", path), indent=2) + "\n"
    if args.out is None:
        sys.stdout.write(text)
        return 0
    with atomic_file(args.out) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return 0


def cmd_batch_retry(args: argparse.Namespace) -> int:
    """Re-run a batch's failed and cancelled jobs; print their ids, one a line."""
    r = Client().request("POST", f"/v1/batches/{batch_path(args.batch_id)}/retry")
    for job_id in r["retried"]:
        print(job_id)
    return 0
