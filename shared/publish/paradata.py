"""Paradata: how an output was made, as W3C PROV (entities, activities, agents) in JSON-LD.

One run of a stage (a CLI command, a job stage, a publish) is one ``prov:Activity``; the files it
read and wrote are ``prov:Entity`` records named by sha256 and size; Graylight itself, at its
version and git revision with the versions of the libraries whose arithmetic shapes the result,
is the ``prov:SoftwareAgent``. The activity carries the parameters as given (the command line)
and as defaulted (every parameter the stage saw), start and end times (UTC, ISO 8601) and the
host. A rig among the inputs adds its figures, and its calibration session's (``rig-report.json``
beside it, written by ``graylight calibrate``). Inputs that an earlier run wrote and recorded
(a ``paradata.json`` beside them naming the same sha256) bring that run's activities in, so one
document holds every step from capture to the file at hand.

The document (``graylight-paradata-v1``)::

    {"@context": {...},                  PROV-O terms and Graylight's own (namespace GL below)
     "format": "graylight-paradata-v1",
     "run": "urn:graylight:run:<uuid>",  the activity this document records (rerun repeats it)
     "summary": ["plain sentences for people"],
     "@graph": [agents, activities, entities]}

Nested records (parameters, versions, rig figures) are JSON literals (``"@type": "@json"``,
JSON-LD 1.1), kept as they are by any processor. An output marked ``volatile`` holds timings or
host paths (a ``report.json``) and is not expected to be identical on a re-run; every other
output is, bit for bit, for the same inputs, parameters and software.
"""

from __future__ import annotations

import getpass
import hashlib
import json
import logging
import os
import platform
import socket
import subprocess
import uuid
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from importlib import metadata
from pathlib import Path
from typing import Any

from shared.core.errors import InputError
from shared.core.files import write_json_atomic
from shared.core.jsonsafe import read_json_bounded
from shared.formats.rig import parse_rig

log = logging.getLogger(__name__)

__all__ = ["GL", "LIBRARIES", "PARADATA_FILE", "PARADATA_FORMAT", "STAGE_PARADATA_FILE", "Run", "build_paradata", "file_entity",
           "load_paradata", "main_activity", "normalised_json_sha256", "paradata_path_for", "rig_figures", "sha256_file", "software",
           "write_paradata"]

PARADATA_FILE = "paradata.json"
#: A job stage's own record in its output folder (hidden: the runner's records are; the job's
#: ``paradata.json`` is the publish stage's).
STAGE_PARADATA_FILE = ".paradata.json"
PARADATA_FORMAT = "graylight-paradata-v1"
#: Graylight's own vocabulary (a namespace for its terms; not fetched by processors).
GL = "https://graylight.org/ns/paradata#"
#: Distributions whose versions can change a result, by the name pip knows them.
LIBRARIES = ("numpy", "numba", "scipy", "opencv-contrib-python-headless", "opencv-python-headless", "opencv-python",
             "open3d", "open3d-cpu", "pymeshlab",
             "fast-simplification", "trimesh", "xatlas", "DracoPy", "laspy", "lazrs", "pye57", "imagecodecs",
             "Pillow", "av")
#: Paradata documents are small (hundreds of files at most); a bound keeps a hostile one cheap.
MAX_PARADATA_BYTES = 16 << 20
# Names of outputs that carry timings or absolute paths, so differ between identical runs.
_VOLATILE_NAMES = {"report.json", "rig-report.json", "calibration.json", "registration.json"}
# Keys of those records that hold timings: left out of their normalised digest.
_TIMING_KEYS = ("seconds", "timings_s", "seconds_")
# Environment variables that shape a run (threads, cache) without being secrets.
_ENV_KEYS = ("GRAYLIGHT_THREADS", "NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "GRAYLIGHT_CACHE_DIR")

CONTEXT: dict[str, Any] = {
    "prov": "http://www.w3.org/ns/prov#",
    "xsd": "http://www.w3.org/2001/XMLSchema#",
    "rdfs": "http://www.w3.org/2000/01/rdf-schema#",
    "gl": GL,
    "Entity": "prov:Entity", "Activity": "prov:Activity", "Agent": "prov:Agent",
    "SoftwareAgent": "prov:SoftwareAgent",
    "label": "rdfs:label",
    "used": {"@id": "prov:used", "@type": "@id", "@container": "@set"},
    "wasGeneratedBy": {"@id": "prov:wasGeneratedBy", "@type": "@id"},
    "wasAssociatedWith": {"@id": "prov:wasAssociatedWith", "@type": "@id"},
    "wasDerivedFrom": {"@id": "prov:wasDerivedFrom", "@type": "@id", "@container": "@set"},
    "wasInformedBy": {"@id": "prov:wasInformedBy", "@type": "@id", "@container": "@set"},
    "startedAtTime": {"@id": "prov:startedAtTime", "@type": "xsd:dateTime"},
    "endedAtTime": {"@id": "prov:endedAtTime", "@type": "xsd:dateTime"},
    "atLocation": "prov:atLocation",
    "format": "gl:format", "run": {"@id": "gl:run", "@type": "@id"}, "summary": {"@id": "gl:summary", "@container": "@list"},
    "stage": "gl:stage", "role": "gl:role", "path": "gl:relativePath", "sha256": "gl:sha256", "sha256Normalised": "gl:sha256Normalised",
    "byteSize": {"@id": "gl:byteSize", "@type": "xsd:integer"}, "volatile": {"@id": "gl:volatile", "@type": "xsd:boolean"},
    "version": "gl:version", "gitRevision": "gl:gitRevision",
    "command": {"@id": "gl:command", "@type": "@json"}, "parameters": {"@id": "gl:parameters", "@type": "@json"},
    "libraries": {"@id": "gl:libraries", "@type": "@json"}, "host": {"@id": "gl:host", "@type": "@json"},
    "rig": {"@id": "gl:rig", "@type": "@json"}, "outcome": "gl:outcome",
}  # fmt: skip


@dataclass
class Run:
    """One run of a stage, as the caller saw it.

    ``inputs`` / ``outputs`` map a role (``capture``, ``out``) to files or folders (folders are
    recorded file by file). ``parameters`` is every parameter the stage used, defaults filled in;
    ``command`` the parameters as given (the command line), when there is one. Times are UTC.
    """

    stage: str
    parameters: Mapping[str, Any]
    inputs: Mapping[str, Sequence[Path]]
    outputs: Mapping[str, Sequence[Path]]
    started: datetime
    ended: datetime
    command: Sequence[str] | None = None
    output_root: Path | None = None
    #: Take an input's sha256 from the record of the run that wrote it (same path and size) instead of
    #: reading it again: for job stages, whose inputs are immutable artifacts; a CLI run re-reads.
    trust_recorded: bool = False
    run_id: str = field(default_factory=lambda: f"urn:graylight:run:{uuid.uuid4()}")


def sha256_file(path: Path, chunk: int = 1 << 20) -> str:
    """Hex sha256 of a file's bytes, read in ``chunk``-byte pieces."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def _git_revision(root: Path) -> str | None:
    """``HEAD`` of the checkout Graylight runs from, ``+dirty`` when it has uncommitted changes; None outside git."""
    try:
        rev = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
                             timeout=5, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=5, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return rev + ("+dirty" if dirty else "") if rev else None


def software() -> dict[str, Any]:
    """Graylight's version and git revision, Python's, and the versions of :data:`LIBRARIES` installed."""
    try:
        version = metadata.version("graylight")
    except metadata.PackageNotFoundError:
        version = "unknown"
    libs: dict[str, str] = {"python": platform.python_version()}
    for name in LIBRARIES:
        try:
            libs[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return {"version": version, "gitRevision": _git_revision(Path(__file__).resolve().parents[2]), "libraries": libs}


def _host() -> dict[str, Any]:
    env = {k: os.environ[k] for k in _ENV_KEYS if k in os.environ}
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cpus = os.cpu_count() or 1
    try:
        user = getpass.getuser()
    except (KeyError, OSError):
        user = None
    return {"name": socket.gethostname(), "platform": platform.platform(), "machine": platform.machine(),
            "cpus": cpus, "user": user, "environment": env}


def _files_of(path: Path) -> list[Path]:
    """The regular files a path names: itself, or every file under a folder (sorted, hidden ones and
    paradata left out)."""
    if path.is_file():
        return [path]
    if not path.is_dir():
        return []
    return sorted(p for p in path.rglob("*") if p.is_file() and not any(part.startswith(".") for part in
                  p.relative_to(path).parts) and p.name != PARADATA_FILE and not p.name.endswith("." + PARADATA_FILE))


def file_entity(path: Path, ident: str, role: str, root: Path | None = None) -> dict[str, Any]:
    """A ``prov:Entity`` for one file: where it was, its sha256 and size, its role, its path relative to ``root``."""
    rel = path.relative_to(root).as_posix() if root is not None and path.is_relative_to(root) else path.name
    return {"@id": ident, "@type": "Entity", "label": path.name, "role": role, "path": rel,
            "atLocation": str(path.resolve()), "sha256": sha256_file(path), "byteSize": path.stat().st_size}


def _strip(value: Any, root: str) -> Any:
    if isinstance(value, dict):
        return {k: _strip(v, root) for k, v in value.items() if not str(k).startswith(_TIMING_KEYS)}
    if isinstance(value, list):
        return [_strip(v, root) for v in value]
    if isinstance(value, str) and value.startswith(root):
        return "<out>" + value[len(root):]
    return value


def normalised_json_sha256(path: Path, out_root: Path) -> str | None:
    """sha256 of a JSON record with its timings left out and paths under ``out_root`` made relative
    (``<out>/...``), sorted keys: equal for two runs that computed the same things. None when the file
    is not JSON."""
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError):
        return None
    text = json.dumps(_strip(doc, str(out_root.resolve())), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def rig_figures(rig_path: Path) -> dict[str, Any] | None:
    """The figures of a rig file (sizes, focal lengths, baseline) and of its calibration session when
    ``graylight calibrate`` made it (the report beside it: reprojection RMS, the board check); None when
    the file is not a rig."""
    from shared.publish.calibration import calibration_report_for

    try:
        # parsed as the rig contract says: any JSON file of an input folder is tried, and one that
        # looked like a rig but held, say, a number for its camera raised a bare AttributeError
        rig = parse_rig(read_json_bounded(rig_path, "rig", missing="rig file not found"), "rig")
    except InputError:
        return None
    out: dict[str, Any] = {"units": rig.units}
    for name, dev in (("camera", rig.camera), ("projector", rig.projector)):
        out[name] = {"size": [dev.width, dev.height], "focal_px": [float(dev.K[0, 0]), float(dev.K[1, 1])],
                     "principal_px": [float(dev.K[0, 2]), float(dev.K[1, 2])], "dist": dev.dist.tolist()}
    out["baseline"] = rig.baseline
    report = calibration_report_for(rig_path)
    if report is not None:
        out["calibration"] = report.summary()
    return out


def paradata_path_for(output: Path) -> Path:
    """Where the paradata of an output lives: ``paradata.json`` inside an output folder,
    ``<name>.paradata.json`` beside an output file."""
    return output / PARADATA_FILE if output.is_dir() else output.with_name(f"{output.name}.{PARADATA_FILE}")


def _recorded(path: Path, digest: str | None) -> tuple[dict[str, Any] | None, list[dict[str, Any]]]:
    """The output entity an earlier run recorded for ``path`` (a ``paradata.json`` or a job stage's
    ``.paradata.json`` in its folder or the two above, naming it by its path relative to that folder
    and, when ``digest`` is given, by the same sha256; else by the same size) and that run's graph."""
    size = path.stat().st_size
    for folder in (path.parent, path.parent.parent, path.parent.parent.parent):
        for name in (f"{path.name}.{PARADATA_FILE}", PARADATA_FILE, STAGE_PARADATA_FILE):
            candidate = folder / name
            if not candidate.is_file() or (name.startswith(path.name) and folder != path.parent):
                continue
            try:
                doc = load_paradata(candidate)
            except InputError:
                continue
            rel = path.relative_to(folder).as_posix()
            for n in doc["@graph"]:
                if n.get("wasGeneratedBy") and n.get("path") in (rel, path.name) and n.get("byteSize") == size \
                        and (digest is None or n.get("sha256") == digest):
                    return n, doc["@graph"]
    return None, []


def build_paradata(run: Run, agent: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The JSON-LD paradata document of one run (see the module's docstring)."""
    agent = dict(agent or software())
    agent_id = f"urn:graylight:software:graylight:{agent['version']}:{agent.get('gitRevision') or 'unknown'}"
    graph: dict[str, dict[str, Any]] = {}
    used: list[str] = []
    rigs: dict[str, Any] = {}
    n = 0
    for role, paths in run.inputs.items():
        for top in paths:
            for f in _files_of(Path(top)):
                n += 1
                prior, earlier = _recorded(f, None) if run.trust_recorded else (None, [])
                if prior is None:
                    ent = file_entity(f, f"{run.run_id}:input:{n}", role, Path(top) if Path(top).is_dir() else None)
                    prior, earlier = _recorded(f, ent["sha256"])
                ent = prior if prior is not None else ent
                used.append(ent["@id"])
                graph.setdefault(ent["@id"], ent)
                for node in earlier:
                    graph.setdefault(node["@id"], node)
                if f.suffix == ".json" and (fig := rig_figures(f)) is not None:
                    ent["rig"] = fig
                    rigs[str(f.resolve())] = fig
    informed = sorted({n["@id"] for n in graph.values() if "Activity" in _types(n)})
    generated: list[dict[str, Any]] = []
    m = 0
    for role, paths in run.outputs.items():
        for top in paths:
            top = Path(top)
            for f in _files_of(top):
                m += 1
                root = run.output_root or (top if top.is_dir() else top.parent)
                ent = file_entity(f, f"{run.run_id}:output:{m}", role, root)
                ent["wasGeneratedBy"] = run.run_id
                ent["wasDerivedFrom"] = list(used)
                ent["volatile"] = f.name in _VOLATILE_NAMES
                if ent["volatile"] and f.suffix == ".json":
                    ent["sha256Normalised"] = normalised_json_sha256(f, root)
                generated.append(ent)
    activity: dict[str, Any] = {
        "@id": run.run_id, "@type": "Activity", "label": f"graylight {run.stage}", "stage": run.stage,
        "parameters": _jsonable(dict(run.parameters)), "startedAtTime": _iso(run.started),
        "endedAtTime": _iso(run.ended), "used": used, "wasAssociatedWith": agent_id, "host": _host(),
    }
    if run.command is not None:
        activity["command"] = list(run.command)
    if informed:
        activity["wasInformedBy"] = informed
    if rigs:
        activity["rig"] = rigs
    agent_node = {"@id": agent_id, "@type": "SoftwareAgent", "label": f"Graylight {agent['version']}",
                  "version": agent["version"], "gitRevision": agent.get("gitRevision"),
                  "libraries": agent.get("libraries", {})}
    if agent_node["gitRevision"] is None:
        del agent_node["gitRevision"]
    nodes = [agent_node, activity, *graph.values(), *generated]
    # Agents of earlier steps (other versions) stay; the same agent is listed once.
    seen: set[str] = set()
    unique = [nd for nd in nodes if not (nd["@id"] in seen or seen.add(nd["@id"]))]
    return {"@context": CONTEXT, "format": PARADATA_FORMAT, "run": run.run_id,
            "summary": _summary(unique, run.run_id), "@graph": unique}


def _types(node: Mapping[str, Any]) -> list[str]:
    t = node.get("@type", [])
    return [t] if isinstance(t, str) else list(t)


def _iso(t: datetime) -> str:
    return t.astimezone(UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def _jsonable(value: Any) -> Any:
    """Parameters as JSON: paths as strings, tuples as lists, anything else by ``str``."""
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if value is None or isinstance(value, bool | int | float | str):
        return value
    return str(value)


def _summary(nodes: Iterable[Mapping[str, Any]], run_id: str) -> list[str]:
    """Plain sentences: one per activity (oldest first), what it read and wrote, with what software."""
    nodes = list(nodes)
    agents = {n["@id"]: n for n in nodes if "SoftwareAgent" in _types(n)}
    acts = sorted((n for n in nodes if "Activity" in _types(n)), key=lambda a: a.get("startedAtTime", ""))
    lines = []
    for a in acts:
        ins = [n for n in nodes if n["@id"] in set(a.get("used", []))]
        outs = [n for n in nodes if n.get("wasGeneratedBy") == a["@id"]]
        ag = agents.get(a.get("wasAssociatedWith"), {})
        host = (a.get("host") or {}).get("name", "an unknown host")
        rev = ag.get("gitRevision")
        lines.append(
            f"{a.get('startedAtTime')} to {a.get('endedAtTime')}: {a.get('label')} on {host} "
            f"(Graylight {ag.get('version', '?')}{f', git {rev[:12]}' if rev else ''}) read {len(ins)} file(s) "
            f"({_bytes(sum(n.get('byteSize', 0) for n in ins))}) and wrote {len(outs)} "
            f"({', '.join(sorted({n.get('path', n.get('label', '')) for n in outs})[:8])}"
            f"{', ...' if len(outs) > 8 else ''})" + (" [this run]" if a["@id"] == run_id else ""))
    return lines


def _bytes(n: int) -> str:
    for unit in ("B", "kB", "MB", "GB"):
        if n < 1000 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n} B"


def write_paradata(path: Path, doc: Mapping[str, Any]) -> Path:
    """Write a paradata document atomically."""
    return write_json_atomic(path, doc)


def load_paradata(path: Path) -> dict[str, Any]:
    """Read and check a paradata document: :class:`InputError` naming the file and field when it is
    not one (another format, no graph, no run activity)."""
    doc = read_json_bounded(path, "paradata", missing="paradata file not found", max_bytes=MAX_PARADATA_BYTES)
    if not isinstance(doc, dict) or doc.get("format") != PARADATA_FORMAT:
        raise InputError(path, f"format: not a {PARADATA_FORMAT} document")
    graph = doc.get("@graph")
    if not isinstance(graph, list) or not all(isinstance(n, dict) and isinstance(n.get("@id"), str) for n in graph):
        raise InputError(path, "@graph: must be a list of nodes with an @id")
    main_activity(doc, path)
    return doc


def main_activity(doc: Mapping[str, Any], where: Path | str = "paradata") -> dict[str, Any]:
    """The activity a paradata document records (its ``run``)."""
    run = doc.get("run")
    for node in doc.get("@graph", []):
        if node.get("@id") == run and "Activity" in _types(node):
            return node
    raise InputError(where, "run: names no activity of the graph")
