"""The runner: executes one stage of one job, holding its lease, idempotently.

In: a stage id (the only thing a message carries). Out: the stage's artifact in the store
and its new state in the database; the stages it unblocks are published.

1. Claim the stage in the database (compare-and-set ``queued -> running`` with a fresh
   lease token). A duplicate or stale message finds it not queued and does nothing.
2. Compute the stage's key from its inputs and parameters. If the store already holds
   that object (a retry, a duplicate, an identical earlier job), finish at once.
3. Otherwise fetch the inputs to local folders, run the adapter into a temporary folder
   while a heartbeat thread renews the lease, store the folder under the key (atomic),
   and mark the stage succeeded — only if the lease is still ours. When the lease is lost
   (the job was cancelled, or the reconciler gave the stage to another worker), the stage
   stops at its next progress report (:class:`LeaseLost`) and nothing is stored.
4. Detached files (:attr:`~shared.service.jobs.StageSpec.detach`, the raw range image) are
   stored as objects of their own before the stage's object. A stage that reads one gets it
   beside the upstream stage's other files; when it has been deleted, the upstream stage's
   adapter runs again here for it. Once the stage's own output is stored (or found), the
   detached inputs it releases (:func:`~shared.service.jobs.released_inputs`) are deleted:
   a stage that fails, or is cancelled, has stored nothing and deletes nothing.

Bad input (:class:`~shared.core.errors.InputError`) fails the stage with its one-line reason
and is never retried; transient faults (connections, timeouts) give the stage back to
the queue and are retried with backoff by Celery; anything else fails the stage.
"""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import socket
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from shared.core.errors import InputError
from shared.service.archive import ArchiveLimits, extract_archive
from shared.service.artifacts import ArtifactError, ArtifactStore, detached_key, sha256_file
from shared.service.capture_cache import release_capture, sweep_captures
from shared.service.config import Settings
from shared.service.faults import storage_fault
from shared.service.jobs import (
    CAPTURE,
    GRAPHS,
    base_name,
    fan_out,
    fanout_index,
    released_inputs,
    root_file,
    row_key,
    stage_spec,
)
from shared.service.jobstore import Job, JobStore, Stage
from shared.service.logs import reset_log_context, set_log_context
from shared.service.queue import publish_stages
from workers.stages import STAGE_FUNCS, StageContext

log = logging.getLogger(__name__)


def transient_errors() -> tuple[type[BaseException], ...]:
    """Exception types worth retrying: the network, the broker, the database, the store."""
    import redis.exceptions
    import sqlalchemy.exc

    types: list[type[BaseException]] = [
        ConnectionError,
        TimeoutError,
        redis.exceptions.ConnectionError,
        redis.exceptions.TimeoutError,
        sqlalchemy.exc.OperationalError,
        sqlalchemy.exc.InterfaceError,
    ]
    try:
        import botocore.exceptions

        types += [botocore.exceptions.EndpointConnectionError, botocore.exceptions.ConnectionClosedError]
    except ImportError:
        pass
    try:
        import aiohttp

        types.append(aiohttp.ClientConnectionError)
    except ImportError:
        pass
    return tuple(types)


TRANSIENT = transient_errors()


def worker_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


class OutputNotStored(Exception):
    """The store would not take or look up a stage's output object (something in the way, a
    permission): the stage's failure says so, naming the object by its key (a content hash, not
    a worker path), for the operator to find in the store."""

    def __init__(self, stage: str, key: str, exc: OSError) -> None:
        self.stage, self.key = stage, key
        super().__init__(f"stage {stage} could not store its output as object {key}: "
                         f"{exc.strerror or type(exc).__name__}; nothing of it was kept")


class LeaseLost(Exception):
    """Raised in a running stage, from its progress callback, once its lease is gone: the job
    was cancelled or the stage was given to another worker, so its work would be dropped."""


class Heartbeat(threading.Thread):
    """Renews a stage's lease every ``interval`` seconds and carries its progress; notes when
    the lease is lost (the reconciler gave the stage to someone else, or the job was cancelled)."""

    def __init__(self, store: JobStore, stage_id: int, token: str, interval: float) -> None:
        super().__init__(name=f"heartbeat-{stage_id}", daemon=True)
        self.store = store
        self.stage_id = stage_id
        self.token = token
        self.interval = interval
        self.progress: float | None = None
        self.lost = threading.Event()
        self._stop_event = threading.Event()

    def set_progress(self, fraction: float) -> None:
        """The stage's progress callback; raises :class:`LeaseLost` when the lease is gone."""
        if self.lost.is_set():
            raise LeaseLost(f"stage {self.stage_id} lost its lease")
        self.progress = fraction

    def renew(self) -> bool:
        """Renew the lease with the current progress; False when it is lost."""
        return self.store.heartbeat(self.stage_id, self.token, self.progress)

    def run(self) -> None:
        while not self._stop_event.wait(self.interval):
            try:
                if not self.renew():
                    log.warning("stage %s: lease lost", self.stage_id)
                    self.lost.set()
                    return
            except Exception as exc:  # the database may blink; the lease survives a missed beat
                log.warning("stage %s: heartbeat failed: %s", self.stage_id, exc)

    def stop(self) -> None:
        self._stop_event.set()
        if self.is_alive():
            self.join(timeout=self.interval + 5)


@dataclass(frozen=True)
class Outcome:
    """What happened to a message: ``skipped`` (not ours to run), ``reused``, ``succeeded``,
    ``failed``, ``lost`` (lease taken away while running) or ``released`` (transient, retried)."""

    status: str
    stage_id: int
    detail: str = ""


def materialize_capture(job: Job, arts: ArtifactStore, settings: Settings) -> Path:
    """A local folder holding the job's capture, unpacked once per machine into the cache."""
    dest = settings.cache_dir / "captures" / job.capture_key
    limits = ArchiveLimits.from_settings(settings)
    require = root_file(job.kind)
    if dest.is_dir():
        return _capture_root(dest, require)
    kind, _, ref = job.capture_ref.partition(":")
    work = settings.cache_dir / "work"
    work.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=work) as tmp:
        if kind == "object":
            folder = arts.fetch(ref, settings.cache_dir)
            manifest = arts.manifest(ref)
            names = sorted(manifest.files) if manifest else []
            if len(names) != 1:
                raise ArtifactError(f"capture object {ref} holds {len(names)} files, expected one archive")
            archive = folder / names[0]
            label = job.name or archive.name
        elif kind == "ref":
            try:
                info = arts.ref_info(ref)
            except FileNotFoundError:
                raise InputError(ref, "no such file or folder in storage") from None
            except ArtifactError as exc:  # a link out of the store (made after intake), a FIFO
                raise InputError("capture_ref", str(exc)) from None
            if info.get("type") == "directory":
                staged = Path(tmp) / "dir"
                try:
                    arts.ref_read(ref, staged, settings.max_unpacked_bytes, settings.max_archive_files)
                except ArtifactError as exc:
                    raise InputError(ref, str(exc).split(": ", 1)[-1]) from None
                dest.parent.mkdir(parents=True, exist_ok=True)
                try:
                    os.rename(staged, dest)
                except OSError:
                    if not dest.is_dir():
                        raise
                return _capture_root(dest, require)
            archive = Path(tmp) / "archive"
            try:
                arts.ref_read(ref, archive, settings.max_upload_bytes, 1)
            except ArtifactError as exc:
                raise InputError(ref, str(exc).split(": ", 1)[-1]) from None
            label = ref
        else:
            raise InputError("capture", f"job has no capture to read ({job.capture_ref!r})")
        return extract_archive(archive, dest, limits, label=label, require=require)


def _capture_root(folder: Path, require: str | None) -> Path:
    if require is None or (folder / require).is_file():
        return folder
    hits = sorted(folder.rglob(require), key=lambda p: len(p.parts))
    if not hits:
        raise InputError(folder.name, f"no {require} in the capture")
    return hits[0].parent


def run_stage(stage_id: int, settings: Settings, retries_left: bool = True, publish: bool = True) -> Outcome:
    """Run one stage (see the module docstring). Transient faults are re-raised after the
    stage is given back to the queue, when ``retries_left``; otherwise they fail it."""
    store = JobStore(settings.database_url)
    claim = store.claim_stage(stage_id, worker_name())
    if claim is None:
        return Outcome("skipped", stage_id)
    job, stage, token = claim.job, claim.stage, claim.token
    if stage.attempts > settings.max_attempts:
        store.fail_stage(stage_id, token, f"gave up after {stage.attempts - 1} attempts; last error: {stage.error or 'worker lost'}")
        return Outcome("failed", stage_id, "too many attempts")
    spec = stage_spec(job.kind, stage.name)
    arts = ArtifactStore(settings.storage_url, settings.s3_endpoint)
    beat = Heartbeat(store, stage_id, token, settings.heartbeat_seconds)
    beat.start()
    log_ids = set_log_context(job=job.id, stage=stage.name, stage_id=stage_id)  # JSON log lines carry them
    try:
        # The row's own dependencies: for a fan-in stage, every instance of the map stage.
        upstream = {d: _output_key(job, d) for d in stage.depends_on}
        key = row_key(job.kind, stage.name, job.capture_key, job.params, upstream)
        store.set_input_key(stage_id, token, key)
        try:
            reused = arts.exists(key)
        except TRANSIENT:
            raise  # a remote store's passing fault: the stage goes back to the queue
        except OSError as exc:  # the object's place in the store is taken by something else
            raise OutputNotStored(stage.name, key, exc) from exc
        if reused:
            log.info("job %s stage %s: output %s exists, reusing", job.id, stage.name, key[:12])
            summary = _stored_json(arts, key, SUMMARY_FILE)
        else:
            summary = _execute(job, stage, spec.inputs, upstream, arts, settings, beat, key)
            if summary is None:
                return Outcome("lost", stage_id)
        # After the output is stored, also when it was found: a run that stored it and stopped
        # before this line left the inputs to its retry.
        _release_inputs(job, spec.name, upstream, arts)
        expand = fan_out(GRAPHS[job.kind], spec.name, int(summary.get("fanout", 0)))
        ok, newly = store.complete_stage(stage_id, token, key, summary, reused=reused, expand=expand)
        if not ok:
            return Outcome("lost", stage_id)
        if publish and newly:
            publish_stages(newly, settings)
        return Outcome("reused" if reused else "succeeded", stage_id)
    except LeaseLost:
        log.info("job %s stage %s: lease lost (cancelled or reassigned); stopped", job.id, stage.name)
        return Outcome("lost", stage_id)
    except InputError as exc:
        msg = _user_facing(exc, job, settings)
        store.fail_stage(stage_id, token, msg)
        return Outcome("failed", stage_id, msg)
    except TRANSIENT as exc:
        reason = f"transient fault: {type(exc).__name__}: {exc}"
        if retries_left:
            store.release_stage(stage_id, token, reason)
            raise
        log.error("job %s stage %s: gave up after retries; %s", job.id, stage.name, reason)
        msg = (f"stage {stage.name} gave up after retries: a connection to the broker, the database or the "
               "store kept failing; the worker's log has the details")
        store.fail_stage(stage_id, token, msg)
        return Outcome("failed", stage_id, msg)
    except Exception as exc:
        from celery.exceptions import SoftTimeLimitExceeded

        if isinstance(exc, SoftTimeLimitExceeded):
            msg = f"stage {stage.name} exceeded its time limit of {spec.time_limit} s"
        elif (fault := storage_fault(exc, stage.name)) is not None:
            log.error("job %s stage %s: %s (%s)", job.id, stage.name, fault, exc)
            msg = fault
        elif isinstance(exc, OutputNotStored):
            log.error("job %s: %s (%r)", job.id, exc, exc.__cause__)
            msg = str(exc)
        else:
            log.exception("job %s stage %s failed", job.id, stage.name)
            msg = unexpected_failure(exc, stage.name, _reading(job, spec.inputs, upstream))
        store.fail_stage(stage_id, token, msg)
        return Outcome("failed", stage_id, msg)
    finally:
        reset_log_context(log_ids)
        beat.stop()
        _release_capture(settings, store, job.id)


def _release_capture(settings: Settings, store: JobStore, job_id: str) -> None:
    """Unpacked captures go when their last unfinished job has ended (issue 21: they count
    against the key): this job's, and any other no unfinished job reads (cancelled while queued)."""
    try:
        release_capture(settings, store, job_id)
        sweep_captures(settings, store)
    except Exception as exc:  # a cache left behind is the next run's to reuse, never a failed stage
        log.warning("job %s: could not remove its unpacked capture: %s", job_id, exc)


def _user_facing(exc: InputError, job: Job, settings: Settings) -> str:
    """The error with a path inside this machine's capture cache replaced by the capture's
    name and the file's path inside it (``scan7.zip:col_02.png: truncated PNG``); any other
    path of this machine's data folder (an upstream stage's output in the object cache) by its
    file name. A failed stage's message never carries an internal worker path."""
    cache = settings.cache_dir / "captures" / job.capture_key
    label = job.name or job.capture_ref
    where = Path(exc.where)
    if where.is_absolute() and where.is_relative_to(cache):
        head = f"{label}:{where.relative_to(cache).as_posix()}"
    elif where.is_absolute() and where.is_relative_to(settings.data_dir):
        head = where.name
    else:
        head = exc.where
    return scrub_paths(f"{head}: {exc.problem}", {cache: f"{label}:", settings.data_dir: ""})


def scrub_paths(text: str, roots: dict[Path, str]) -> str:
    """``text`` with every path under one of ``roots`` rewritten: the root replaced by its label
    (``scan7.zip:``) when the label is not empty, else the path reduced to its file name."""
    for root, label in roots.items():
        pattern = re.escape(str(root).rstrip("/")) + r"/[^\s:'\"]*"
        text = re.sub(pattern, lambda m, r=root, lab=label: (lab + Path(m.group()).relative_to(r).as_posix()) if lab
                      else Path(m.group()).name, text)
    return text


def _reading(job: Job, inputs: tuple[str, ...], upstream: dict[str, str]) -> str:
    """What a stage reads, as its failure message names it: the capture (by the name it was
    submitted under) or the outputs of the stages before it."""
    parts = []
    if CAPTURE in inputs and not job.capture_ref.startswith("none:"):
        parts.append(f"the capture {job.name or job.capture_ref.partition(':')[2][:12]}")
    if upstream:
        names = sorted({base_name(n) for n in upstream})
        parts.append(f"the output of {', '.join(names)}")
    return " and ".join(parts) or "its parameters"


def unexpected_failure(exc: BaseException, stage: str, reading: str) -> str:
    """One line for a stage that failed on something no check foresaw: the stage and what it was
    reading, never the bare exception (``MemoryError``, ``OverflowError: int too big ...``) nor a
    path; the traceback is in the worker's log."""
    if isinstance(exc, MemoryError):
        what = "ran out of memory"
    elif isinstance(exc, RecursionError):
        what = "met input nested too deeply"
    elif isinstance(exc, ArithmeticError):  # OverflowError among them
        what = "met a number out of range"
    else:
        what = "failed unexpectedly"
    return f"stage {stage} {what} while reading {reading}; the worker's log has the details"


#: File in every stage object holding the stage's summary (hidden from artifact listings);
#: a stage that finds its output stored reads its summary (say, how many pieces it fans out
#: into) from here.
SUMMARY_FILE = ".summary.json"


def _stored_json(arts: ArtifactStore, key: str, name: str) -> dict:
    """The JSON file ``name`` of stored object ``key`` ({} when the object has none)."""
    m = arts.manifest(key)
    if m is None or name not in m.files:
        return {}
    with arts.open(key, name) as f:
        return json.loads(f.read().decode())


def _output_key(job: Job, name: str) -> str:
    st = job.stage(name)
    if st.output_key is None:
        raise ArtifactError(f"job {job.id}: input stage {name} has no output")
    return st.output_key


#: File in every stage object that detached files (hidden from artifact listings): each detached
#: file's size and SHA-256, against which a re-made copy is checked.
DETACHED_FILE = ".detached.json"


def _execute(
    job: Job,
    stage: Stage,
    inputs: tuple[str, ...],
    upstream: dict[str, str],
    arts: ArtifactStore,
    settings: Settings,
    beat: Heartbeat,
    key: str,
) -> dict | None:
    """Run the adapter into a temporary folder and store it as object ``key`` (its detached
    files first, each as its own object); the summary, or None when the lease was lost
    meanwhile (then nothing is stored)."""
    spec = stage_spec(job.kind, stage.name)
    work = settings.cache_dir / "work"
    work.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f"{stage.name}-", dir=work))
    try:
        local_inputs = {name: arts.fetch(k, settings.cache_dir) for name, k in upstream.items()}
        for ref in spec.detached_inputs:
            producer, _, name = ref.partition("/")
            if producer in local_inputs:
                local_inputs[producer] = _with_detached(job, producer, name, local_inputs[producer], upstream[producer],
                                                        arts, settings, beat, tmp / "inputs" / producer)  # fmt: skip
        out = tmp / "out"
        out.mkdir()
        summary = public_summary(_run_adapter(job, stage.name, inputs, local_inputs, arts, settings, beat, out), out, work)
        summary["published"] = [n for n in spec.publish if (out / n).is_file()]  # the links the API gives
        if beat.lost.is_set():
            # Someone else holds the stage now; their run will store the same object.
            return None
        (out / SUMMARY_FILE).write_text(json.dumps(summary, default=str))
        detached = {}
        for name in spec.detach:
            if (out / name).is_file():
                detached[name] = {"size": (out / name).stat().st_size, "sha256": sha256_file(out / name)}
                _store_detached(arts, key, name, out / name, tmp)
        if detached:
            (out / DETACHED_FILE).write_text(json.dumps(detached, sort_keys=True))
        try:
            arts.put_dir(key, out, move=True)
        except TRANSIENT:
            raise
        except OSError as exc:
            raise OutputNotStored(stage.name, key, exc) from exc
        return summary
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def public_summary(doc: Any, out: Path, work: Path) -> Any:
    """A stage's summary as the API shows it: a path inside its output folder ``out`` becomes the
    published file's name (``preview.mp4``), and no other path of this worker's scratch folder
    ``work`` is kept (it names nothing a client can reach)."""
    if isinstance(doc, dict):
        return {k: public_summary(v, out, work) for k, v in doc.items()}
    if isinstance(doc, list):
        return [public_summary(v, out, work) for v in doc]
    if isinstance(doc, str) and doc.startswith("/"):
        p = Path(doc)
        if p.is_relative_to(out):
            return p.relative_to(out).as_posix() or "."
        if p.is_relative_to(work) or p.is_relative_to(work.parent):
            return p.name
    return doc


def _run_adapter(job: Job, name: str, inputs: tuple[str, ...], local_inputs: dict[str, Path], arts: ArtifactStore,
                 settings: Settings, beat: Heartbeat, out: Path) -> dict:
    """Run stage row ``name``'s adapter on ``local_inputs`` (upstream row -> folder) into the empty
    folder ``out``; its summary."""
    # A probe job has no capture; its random capture key only makes its output its own.
    has_capture = CAPTURE in inputs and not job.capture_ref.startswith("none:")
    capture_dir = materialize_capture(job, arts, settings) if has_capture else None
    rig_key = job.params.get("rig")
    rig_path = arts.fetch(rig_key, settings.cache_dir) / "rig.json" if isinstance(rig_key, str) else None
    ctx = StageContext(
        job_id=job.id, kind=job.kind, stage=name, params=dict(job.params), capture_dir=capture_dir,
        inputs=local_inputs, out_dir=out, progress=beat.set_progress, rig_path=rig_path,
        index=fanout_index(name),
    )  # fmt: skip
    return STAGE_FUNCS[base_name(name)](ctx) or {}


def _store_detached(arts: ArtifactStore, key: str, name: str, src: Path, tmp: Path) -> None:
    """Move the file ``src`` out of a stage's output into object ``detached_key(key, name)``."""
    folder = Path(tempfile.mkdtemp(prefix="detached-", dir=tmp))
    target = folder / name
    target.parent.mkdir(parents=True, exist_ok=True)
    os.replace(src, target)
    arts.put_dir(detached_key(key, name), folder, move=True)


def _with_detached(job: Job, producer: str, name: str, folder: Path, key: str, arts: ArtifactStore,
                   settings: Settings, beat: Heartbeat, view: Path) -> Path:
    """A folder ``view`` holding the files of upstream output ``folder`` (object ``key`` of row
    ``producer``), as links, and its detached file ``name``, hard-linked (or copied) so that a
    concurrent deletion of the detached object cannot take it away from this run. When the
    detached object is gone (a job that did not keep it released it), ``producer``'s adapter
    runs again to store it. An output stored before files were detached still holds the file."""
    view.mkdir(parents=True)
    for p in folder.iterdir():
        (view / p.name).symlink_to(p)
    if (folder / name).is_file():
        return view
    dkey = detached_key(key, name)
    for attempt in range(3):
        if not arts.exists(dkey):
            _remake_detached(job, producer, key, arts, settings, beat)
        (view / name).unlink(missing_ok=True)
        try:
            _pin(arts.fetch(dkey, settings.cache_dir) / name, view / name)
            return view
        except (ArtifactError, FileNotFoundError):
            if attempt == 2:
                raise
            log.info("job %s: the detached %s of %s went away while read; again", job.id, name, producer)
    raise AssertionError("unreachable")  # pragma: no cover


def _pin(src: Path, dst: Path) -> None:
    """``dst`` a hard link to ``src`` (a copy across filesystems): it outlives ``src``'s deletion."""
    try:
        os.link(src, dst)
    except FileNotFoundError:
        raise
    except OSError:
        shutil.copyfile(src, dst)


def _remake_detached(job: Job, producer: str, key: str, arts: ArtifactStore, settings: Settings,
                     beat: Heartbeat) -> None:
    """Store the detached files of row ``producer``'s output (object ``key``) again, from a new
    run of its adapter on its own inputs (its other files are stored already and left alone)."""
    spec = stage_spec(job.kind, producer)
    row = job.stage(producer)
    upstream = {d: _output_key(job, d) for d in row.depends_on}
    if row_key(job.kind, producer, job.capture_key, job.params, upstream) != key:
        raise ArtifactError(f"job {job.id}: the inputs of {producer} changed since its output {key[:12]} was stored")
    log.info("job %s: %s of %s was deleted; running %s again for it", job.id, ", ".join(spec.detach), producer, producer)
    stored = _stored_json(arts, key, DETACHED_FILE)
    work = settings.cache_dir / "work"
    work.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f"{producer}-detached-", dir=work))
    try:
        local_inputs = {d: arts.fetch(k, settings.cache_dir) for d, k in upstream.items()}
        out = tmp / "out"
        out.mkdir()
        _run_adapter(job, producer, spec.inputs, local_inputs, arts, settings, beat, out)
        for name in spec.detach:
            src = out / name
            if not src.is_file():
                raise ArtifactError(f"job {job.id}: {producer} ran again but wrote no {name}")
            want = stored.get(name)
            if want is not None and want.get("sha256") != sha256_file(src):
                # The store's rule for an object rebuilt under its key: the new bytes stand.
                log.warning("job %s: %s of %s came out different when made again", job.id, name, producer)
            _store_detached(arts, key, name, src, tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _release_inputs(job: Job, stage: str, upstream: dict[str, str], arts: ArtifactStore) -> None:
    """Delete the detached inputs stage row ``stage`` has made redundant (its output is stored)."""
    for ref in released_inputs(stage_spec(job.kind, stage), job.params):
        producer, _, name = ref.partition("/")
        if producer not in upstream:
            continue
        dkey = detached_key(upstream[producer], name)
        if arts.exists(dkey):
            arts.delete(dkey)
            log.info("job %s stage %s: deleted the detached %s of %s (%s)", job.id, stage, name, producer, dkey[:12])
