"""Jobs and stages: their states, the allowed transitions, and the job graphs as data.

This is the one module the API, the workers and the reconciler share for what a job is.
A job of a given ``kind`` runs the stages of :func:`graph_for` ``(kind)``; each
:class:`StageSpec` names its inputs (``"capture"`` — the submitted capture — or an
upstream stage), the queue it runs on, its time limit, and the files of its output that
the API publishes under short names (``cloud.ply``). Later stages (multi-view merge,
compression) plug in by appearing here and in ``workers.stages`` without touching the runner.

A *map* stage (``fanout_from``) has no row when the job is created: when the stage it fans
out from succeeds, its summary's ``fanout`` count gives the number of instances
(``tiles_chunk#0``, ``tiles_chunk#1`` ...), each its own task, and every stage that reads the
map stage reads all of them; the database counts the fan-in (no Celery chords).

Stage outputs are addressed by :func:`stage_key`: a SHA-256 of the stage, its version,
its parameters and the keys of its inputs, so identical work is found, not redone.

A stage may *detach* files of its output (``detach``): each is stored as an object of its own
(:func:`shared.service.artifacts.detached_key` of the stage's key and the file's name), so that
a later stage can delete it when it has made it redundant, although stored objects never change.
The stages that read it name it in ``detached_inputs`` (the runner lays it beside the other
files of the upstream output, and runs the upstream stage again for it if it has been deleted);
``release_unless`` names the job parameter that, when false, deletes those inputs once the
stage's own output is stored: the raw range image once ``range.glr`` is, when
``params.compress.keep_range`` is false.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from enum import StrEnum
from typing import Any


class JobState(StrEnum):
    QUEUED = "queued"
    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELLED = "cancelled"


class StageState(StrEnum):
    PENDING = "pending"  # waiting for its inputs
    QUEUED = "queued"  # inputs ready, a message is (or should be) on the broker
    RUNNING = "running"  # a worker holds its lease
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELLED = "cancelled"


JOB_TERMINAL = frozenset({JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELLED})
STAGE_TERMINAL = frozenset({StageState.SUCCEEDED, StageState.FAILED, StageState.CANCELLED})

#: Allowed job state changes. ``succeeded -> queued`` is a retry after inputs changed
#: (or the nightly preview re-render); ``failed``/``cancelled -> queued`` is a retry.
JOB_TRANSITIONS: dict[JobState, frozenset[JobState]] = {
    JobState.QUEUED: frozenset({JobState.RUNNING, JobState.CANCELLED, JobState.FAILED, JobState.SUCCEEDED}),
    JobState.RUNNING: frozenset({JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELLED, JobState.QUEUED}),
    JobState.SUCCEEDED: frozenset({JobState.QUEUED}),
    JobState.FAILED: frozenset({JobState.QUEUED}),
    JobState.CANCELLED: frozenset({JobState.QUEUED}),
}

#: Allowed stage state changes. ``running -> queued`` happens when a lease expires (the
#: reconciler) or a transient fault is retried; ``succeeded -> pending`` when a retry finds
#: that the stage's inputs changed.
STAGE_TRANSITIONS: dict[StageState, frozenset[StageState]] = {
    StageState.PENDING: frozenset({StageState.QUEUED, StageState.CANCELLED}),
    # queued -> failed: the reconciler's verdict on a stage whose messages keep killing workers.
    StageState.QUEUED: frozenset({StageState.RUNNING, StageState.CANCELLED, StageState.SUCCEEDED, StageState.FAILED}),
    StageState.RUNNING: frozenset(
        {StageState.SUCCEEDED, StageState.FAILED, StageState.QUEUED, StageState.CANCELLED}
    ),
    StageState.SUCCEEDED: frozenset({StageState.PENDING}),
    StageState.FAILED: frozenset({StageState.PENDING}),
    StageState.CANCELLED: frozenset({StageState.PENDING}),
}


def can_move_job(old: str, new: str) -> bool:
    """Whether a job may go from state ``old`` to ``new``."""
    return JobState(new) in JOB_TRANSITIONS[JobState(old)]


def can_move_stage(old: str, new: str) -> bool:
    """Whether a stage may go from state ``old`` to ``new``."""
    return StageState(new) in STAGE_TRANSITIONS[StageState(old)]


def stage_sources(new: str) -> frozenset[StageState]:
    """The stage states from which a stage may move to ``new`` (the job store's WHERE clauses)."""
    return frozenset(old for old, targets in STAGE_TRANSITIONS.items() if StageState(new) in targets)


#: Jobs that are not final: the reconciler re-derives their state.
JOB_ACTIVE = frozenset(JobState) - JOB_TERMINAL
#: Stages that wait for their turn; a failed stage cancels these downstream.
STAGE_WAITING = frozenset({StageState.PENDING, StageState.QUEUED})


class IllegalTransition(RuntimeError):
    """A state change that :data:`JOB_TRANSITIONS` / :data:`STAGE_TRANSITIONS` do not allow:
    a bug in the job service, never a user error."""


def check_transition(stage: str | None, old: str | None, new: str) -> None:
    """Raise :class:`IllegalTransition` unless a job (``stage`` None) or a stage may move from
    ``old`` to ``new``; ``old`` None is a creation."""
    if old is None:
        return
    ok = can_move_job(old, new) if stage is None else can_move_stage(old, new)
    if not ok:
        what = "job" if stage is None else f"stage {stage}"
        raise IllegalTransition(f"{what}: {old} -> {new} is not a declared transition")


#: The logical queues a stage runs on (``control`` carries the reconciler and beat's tasks);
#: the broker's names carry ``GRAYLIGHT_QUEUE_PREFIX`` in front.
QUEUES: tuple[str, ...] = ("cpu", "render", "control")

#: The input name that refers to the job's submitted capture (or calibration session).
CAPTURE = "capture"


@dataclass(frozen=True)
class StageSpec:
    """One stage of a job graph.

    ``inputs`` are ``"capture"`` and/or names of earlier stages; ``queue`` is the logical
    queue (``cpu`` or ``render``); ``time_limit`` is seconds (hard; the soft limit is 90 %);
    ``publish`` are output files the API also serves under their bare name;
    ``version`` enters the output key, so bumping it makes retries re-run the stage.
    ``detach``: files of the output stored as objects of their own (deletable; see the module
    docstring); ``detached_inputs``: detached files of upstream stages this stage reads, as
    ``"stage/file"``; ``release_unless``: a dotted job parameter (``"compress.keep_range"``)
    that, when false, has the runner delete ``detached_inputs`` once this stage's output is stored.
    """

    name: str
    queue: str
    inputs: tuple[str, ...]
    time_limit: int
    publish: tuple[str, ...] = ()
    version: int = 1
    params: tuple[str, ...] = ()  # job parameters that enter this stage's key
    switch: str | None = None  # a job parameter that, when false, leaves this stage out
    fanout_from: str | None = None  # a map stage: one instance per item counted by that stage
    detach: tuple[str, ...] = ()
    detached_inputs: tuple[str, ...] = ()
    release_unless: str | None = None
    # Short names a published file is also served under, as (alias, file): a multi-view job's
    # merged.ply is its cloud.ply, so every kind answers the same links.
    aliases: tuple[tuple[str, str], ...] = ()
    # Upstream stages read when the job runs them and left out of the inputs when it does not
    # (a multi-view preview uses the derivatives unless {"derivatives": false}).
    optional: tuple[str, ...] = ()
    # The stage's share of a job's work, relative to the others (job progress weighs each
    # stage's own fraction by it): its typical run time in units of a scan's triangulation, at
    # full size (a 15 MP capture, an 8-view set, the default 1280x720 10 s preview: decode about
    # 3x triangulation, a merge 27-76 s against 2-4 s, preview frames rendered on the CPU). Rough
    # on purpose: it only has to keep the job's progress moving with the work. A map stage's
    # weight is the share of all its instances together (a set's 8 views decoded: 8 x 3).
    weight: float = 1.0

    @property
    def is_map(self) -> bool:
        return self.fanout_from is not None

    @property
    def depends_on(self) -> tuple[str, ...]:
        """Upstream stages (inputs other than the capture)."""
        return tuple(i for i in self.inputs if i != CAPTURE)

    def published_file(self, short: str) -> str | None:
        """The file of this stage's output served under the short name ``short``, or None."""
        if short in self.publish:
            return short
        return next((f for a, f in self.aliases if a == short and f in self.publish), None)

    @property
    def short_names(self) -> tuple[str, ...]:
        """Every short name this stage publishes: its files, then its aliases."""
        return (*self.publish, *(a for a, f in self.aliases if f in self.publish))

    def published_names(self, summary: Mapping[str, Any] | None) -> tuple[str, ...]:
        """The short names a finished row of this stage serves: those of the files its summary's
        ``published`` list says it wrote (a stage may write only some of them: the merged cloud
        or the views' range images), or all of :attr:`short_names` for an older summary."""
        wrote = (summary or {}).get("published")
        if not isinstance(wrote, list):
            return self.short_names
        return tuple(n for n in self.short_names if self.published_file(n) in wrote)


#: The level-of-detail meshes a merge writes (shared.merge.pipeline: ``mesh_lod{k}.glb`` for the
#: default ``MeshParams.lods``, 1/4, 1/16 and 1/64 of the faces), published by their names.
MESH_LOD_FILES: tuple[str, ...] = ("mesh_lod1.glb", "mesh_lod2.glb", "mesh_lod3.glb")

#: The interchange files the export stage writes of a job's cloud (a scan's, or the merged one).
EXPORT_FILES: tuple[str, ...] = ("cloud.laz", "cloud.copc.laz", "cloud.e57")
#: What the publish stage serves by name (shared.publish.folder; the scene's derivatives are in its folder).
PUBLISH_FILES: tuple[str, ...] = ("scene.svx.json", "qa.json", "qa.html", "paradata.json")
#: The job parameters naming the object (title, collection, identifier: shared.service.params).
OBJECT_PARAMS: tuple[str, ...] = ("title", "collection", "identifier")
#: The derivative GLBs a ``derivatives`` stage may write (shared.derive.levels: the job parameter
#: accepts these level names only, so that every file it writes is published by its name).
DERIVATIVE_FILES: tuple[str, ...] = tuple(f"mesh_{n}.glb" for n in ("thumb", "low", "medium", "high", "highest"))

GRAPHS: dict[str, tuple[StageSpec, ...]] = {
    "scan": (
        StageSpec("ingest", "cpu", (CAPTURE,), 600, publish=("capture.json",), params=("rig",), weight=0.5),
        StageSpec("decode", "cpu", (CAPTURE, "ingest"), 3600, publish=("decoded.npz",), weight=3.0),
        StageSpec("triangulate", "cpu", (CAPTURE, "ingest", "decode"), 3600,
                  publish=("cloud.ply", "triangulate.json"), params=("rig",), detach=("range.npz",)),
        # The range image compressed (range.glr); the raw range.npz is published from here
        # unless params.compress.keep_range is false, and then no longer stored at all once
        # range.glr is (triangulate's detached copy is deleted).
        StageSpec("compress", "cpu", ("triangulate",), 3600, publish=("range.glr", "range.npz", "compress.json"),
                  params=("compress",), detached_inputs=("triangulate/range.npz",),
                  release_unless="compress.keep_range", weight=1.0),
        # Tiles fan out: a plan, one task per chunk (subtree), a merge (fan-in counted in the
        # database). The merge keeps the name "tiles": its folder is what viewers load.
        StageSpec("tiles_plan", "render", ("triangulate",), 7200, switch="render", params=("tiles",), weight=0.5),
        StageSpec("tiles_chunk", "render", ("tiles_plan",), 7200, switch="render", fanout_from="tiles_plan", weight=1.5),
        StageSpec("tiles", "render", ("tiles_plan", "tiles_chunk"), 7200, switch="render"),
        StageSpec("preview", "render", ("tiles",), 7200, publish=("preview.mp4", "preview.png"),
                  params=("preview", "preview_epoch"), switch="render", weight=6.0),
        # The cloud in the formats GIS and survey software read (LAS 1.4 LAZ, COPC, E57).
        # CPU work (LAZ compression), so it runs on the cpu queue; {"export": false} skips it.
        StageSpec("export", "cpu", ("triangulate",), 7200, publish=EXPORT_FILES, switch="export", version=2, weight=2.0),
        # The object as a museum publishes it (shared.publish): Voyager scene, quality report, the job's paradata.
        StageSpec("publish", "cpu", (CAPTURE, "triangulate"), 1800, publish=PUBLISH_FILES, weight=1.0,
                  params=OBJECT_PARAMS),
    ),
    "calibrate": (
        StageSpec("calibrate", "cpu", (CAPTURE,), 3600, publish=("rig.json", "calibration.json", "paradata.json")),
    ),
    # A multi-view scan set (graylight-scanset-v1): a plan that validates it and fans out three
    # tasks per view, each its own task so that workers on several machines share one object:
    # ingest, decode, triangulate (instance i of each reads instance i of the one before), then
    # the merge (register, fuse, mesh) of all views, then tiles and preview of the merged cloud.
    "multiview": (
        StageSpec("mv_plan", "cpu", (CAPTURE,), 600, publish=("scanset.json",), weight=0.5),
        StageSpec("mv_ingest", "cpu", (CAPTURE, "mv_plan"), 600, fanout_from="mv_plan", weight=4.0),
        StageSpec("mv_decode", "cpu", (CAPTURE, "mv_ingest"), 3600, fanout_from="mv_plan", weight=24.0),
        StageSpec("mv_triangulate", "cpu", (CAPTURE, "mv_ingest", "mv_decode"), 3600, fanout_from="mv_plan",
                  weight=8.0),
        StageSpec("mv_merge", "cpu", (CAPTURE, "mv_plan", "mv_decode", "mv_triangulate"), 7200,
                  publish=("merged.ply", "registration.json", "mesh.glb", "mesh.ply", "report.json",
                           *MESH_LOD_FILES),
                  params=("drop_unregistered",), aliases=(("cloud.ply", "merged.ply"),), weight=16.0),
        # Textured web derivatives of the merge (shared.derive): one Draco GLB per level;
        # {"derivatives": false} leaves them out, an object chooses levels and colour.
        StageSpec("derivatives", "cpu", ("mv_merge",), 7200, publish=(*DERIVATIVE_FILES, "derivatives.json"),
                  params=("derivatives",), switch="derivatives"),
        # The object compressed: the merged cloud (merged.glo) or the views' range images
        # (ranges/*.glr), whichever is smaller.
        StageSpec("mv_compress", "cpu", ("mv_merge",), 3600, publish=("merged.glo", "compress.json"), params=("compress",)),
        StageSpec("tiles_plan", "render", ("mv_merge",), 7200, switch="render", params=("tiles",), weight=0.5),
        StageSpec("tiles_chunk", "render", ("tiles_plan",), 7200, switch="render", fanout_from="tiles_plan", weight=1.5),
        StageSpec("tiles", "render", ("tiles_plan", "tiles_chunk"), 7200, switch="render"),
        # The merged model orbits its turntable axis (mv_merge's registration.json), drawn as
        # its textured derivative when the job makes them (else as the tiles' points).
        StageSpec("preview", "render", ("tiles", "mv_merge", "derivatives"), 7200, publish=("preview.mp4", "preview.png"),
                  params=("preview", "preview_epoch"), switch="render", weight=6.0, optional=("derivatives",)),
        # The merged cloud in the interchange formats, as a scan's cloud is.
        StageSpec("export", "cpu", ("mv_merge",), 7200, publish=EXPORT_FILES, switch="export", version=2, weight=2.0),
        # Publishes the derivatives when the job makes them, else the merge's own levels.
        StageSpec("publish", "cpu", (CAPTURE, "mv_merge", "derivatives"), 1800, publish=PUBLISH_FILES, weight=1.0,
                  params=OBJECT_PARAMS, optional=("derivatives",)),
    ),
    # A service self-test: one trivial stage that sleeps params["seconds"] (at most 60) and
    # writes probe.json. It measures queue overhead and proves the workers are alive.
    "probe": (StageSpec("probe", "cpu", (CAPTURE,), 120, publish=("probe.json",), params=("seconds",)),),
}  # fmt: skip


#: The file that marks the root folder of a job kind's submitted archive.
ROOT_FILES: dict[str, str] = {"scan": "capture.json", "calibrate": "board.json", "multiview": "scanset.json"}


def root_file(kind: str) -> str | None:
    """The file a ``kind`` job's archive must hold (its folder is the capture root), or None."""
    return ROOT_FILES.get(kind)


def graph_for(kind: str, params: Mapping[str, Any] | None = None) -> tuple[StageSpec, ...]:
    """The stages a new job of ``kind`` runs, in topological order: those switched off by the job's parameters (``{"render": false}`` skips tiles and
    preview), are left out together with everything downstream of them."""
    if kind not in GRAPHS:
        raise KeyError(kind)
    params = params or {}
    kept: list[StageSpec] = []
    names: set[str] = set()
    for spec in GRAPHS[kind]:
        if spec.switch is not None and params.get(spec.switch, True) is False:
            continue
        missing = [d for d in spec.depends_on if d not in names]
        if missing and all(d in spec.optional for d in missing):
            spec = replace(spec, inputs=tuple(i for i in spec.inputs if i not in missing))
            missing = []
        if not missing:
            kept.append(spec)
            names.add(spec.name)
    return tuple(kept)


def released_inputs(spec: StageSpec, params: Mapping[str, Any]) -> tuple[str, ...]:
    """The detached inputs (``"stage/file"``) that a succeeded ``spec`` stage of a job with
    ``params`` makes redundant: its ``detached_inputs`` when the job parameter its
    ``release_unless`` names is false (absent counts as true), else none. The parameter enters
    the stage's key (it is read from ``spec.params``), so a stored output decides the same."""
    if spec.release_unless is None:
        return ()
    value: Any = params
    for part in spec.release_unless.split("."):
        value = value.get(part, True) if isinstance(value, Mapping) else True
    return spec.detached_inputs if value is False else ()


def stage_spec(kind: str, name: str) -> StageSpec:
    """The declared spec of stage ``name`` (or of a map stage's row ``name#i``) in graph ``kind``."""
    name = base_name(name)
    for spec in GRAPHS[kind]:
        if spec.name == name:
            return spec
    raise KeyError(f"{kind}.{name}")


def all_stage_specs() -> dict[str, StageSpec]:
    """Every declared stage by name (one Celery task each)."""
    out: dict[str, StageSpec] = {}
    for specs in GRAPHS.values():
        for spec in specs:
            out.setdefault(spec.name, spec)
    return out


def longest_time_limit() -> int:
    """The longest stage time limit in seconds (the broker's visibility timeout must exceed it)."""
    return max(s.time_limit for s in all_stage_specs().values())


#: Separates a map stage's name from the index of one of its instances (``tiles_chunk#3``).
FANOUT_SEP = "#"


def base_name(stage: str) -> str:
    """The spec name of a stage row (``tiles_chunk#3`` -> ``tiles_chunk``)."""
    return stage.split(FANOUT_SEP, 1)[0]


def fanout_index(stage: str) -> int | None:
    """The instance index of a map stage's row (``tiles_chunk#3`` -> 3), None for other stages."""
    _, sep, idx = stage.partition(FANOUT_SEP)
    return int(idx) if sep else None


@dataclass(frozen=True)
class InstanceRow:
    """One row a finished stage fans out into: instance ``name`` (``mv_decode#2``) of a map
    stage, on ``queue``, waiting for the rows ``depends_on``."""

    name: str
    queue: str
    depends_on: tuple[str, ...]


@dataclass(frozen=True)
class FanOut:
    """What a finished stage fans out into: the map stages ``maps`` (replacing any instances
    they had) and their instance ``rows``; no rows when the stage counted no items, and the
    stages downstream then read none."""

    maps: tuple[str, ...]
    rows: tuple[InstanceRow, ...]


def fan_out(graph: Iterable[StageSpec], parent: str, count: int) -> FanOut:
    """The rows of every map stage of ``graph`` that fans out from stage ``parent``, ``count``
    instances each, in graph order (all instances of one map stage, then the next).

    Instance ``i`` of a map stage reads instance ``i`` of a sibling map stage it names as an
    input (one that fans out from the same parent): a chain of per-item stages, such as a
    view's ingest, decode and triangulate, runs item by item, each step its own task. Any other
    upstream stage it names is read whole.
    """
    maps = [m for m in graph if m.fanout_from == parent]
    siblings = {m.name for m in maps}
    rows: list[InstanceRow] = []
    for m in maps:
        for i in range(count):
            deps = tuple(f"{d}{FANOUT_SEP}{i}" if d in siblings else d for d in m.depends_on)
            rows.append(InstanceRow(f"{m.name}{FANOUT_SEP}{i}", m.queue, deps))
    return FanOut(tuple(m.name for m in maps), tuple(rows))


def stage_key(
    spec: StageSpec, capture_key: str, params: Mapping[str, Any], upstream: Mapping[str, str], index: int | None = None
) -> str:
    """Content address of a stage's output: SHA-256 (hex) of the stage name and version, the
    parameters it reads, the capture's key (when it reads the capture), the keys of the
    upstream stage rows it reads (``upstream``: row name -> key) and, for an instance of a
    map stage, its index."""
    doc = {
        "stage": spec.name,
        "version": spec.version,
        "params": {p: params.get(p) for p in spec.params},
        "capture": capture_key if CAPTURE in spec.inputs else None,
        "upstream": {d: upstream[d] for d in sorted(upstream)},
        "index": index,
    }
    blob = json.dumps(doc, sort_keys=True, separators=(",", ":"), default=str).encode()
    return hashlib.sha256(blob).hexdigest()


def row_key(
    kind: str, row: str, capture_key: str, params: Mapping[str, Any], upstream: Mapping[str, str]
) -> str:
    """:func:`stage_key` of the job row ``row`` (a stage, or a map stage's instance ``name#i``)
    of a ``kind`` job: the one place the runner, the retry route and the reconciler compute it."""
    return stage_key(stage_spec(kind, row), capture_key, params, upstream, fanout_index(row))


@dataclass
class StageView:
    """What the graph logic needs of a stage row: its name, state and dependencies."""

    name: str
    state: str
    depends_on: tuple[str, ...] = field(default_factory=tuple)
    output_key: str | None = None


def ready_to_queue(stages: Iterable[StageView]) -> list[str]:
    """Names of pending stages whose upstream stages have all succeeded (the fan-in count)."""
    stages = list(stages)
    done = {s.name for s in stages if s.state == StageState.SUCCEEDED}
    return [s.name for s in stages if s.state == StageState.PENDING and all(d in done for d in s.depends_on)]


def job_fraction(kind: str, stages: Iterable[tuple[str, str, float]]) -> float:
    """The finished fraction of a ``kind`` job from its stage rows ``(name, state, progress)``:
    each stage counts its own progress (1 when succeeded), weighed by its spec's ``weight``, so a
    long merge moves the job as far as it does its own work, not one stage in twenty. A map
    stage's weight is that of all its instances together (their mean progress), counted from
    the moment its parent has a row, so the fraction does not fall when a stage fans out."""
    groups: dict[str, list[float]] = {}
    for name, state, progress in stages:
        frac = 1.0 if state == StageState.SUCCEEDED else min(max(float(progress), 0.0), 1.0)
        groups.setdefault(base_name(name), []).append(frac)
    done = total = 0.0
    for spec in GRAPHS.get(kind, ()):
        members = groups.get(spec.name)
        if members is None and not (spec.is_map and spec.fanout_from in groups):
            continue  # switched off (or not part of this job)
        total += spec.weight
        if members:
            done += spec.weight * sum(members) / len(members)
        elif spec.fanout_from is not None and min(groups[spec.fanout_from]) >= 1.0:
            done += spec.weight  # its parent counted nothing to fan out into
    return done / total if total else 0.0


def job_state_from_stages(states: Iterable[str], cancelled: bool = False) -> JobState:
    """The job state its stages imply."""
    states = [StageState(s) for s in states]
    if cancelled:
        return JobState.CANCELLED
    if any(s == StageState.FAILED for s in states):
        return JobState.FAILED
    if states and all(s == StageState.SUCCEEDED for s in states):
        return JobState.SUCCEEDED
    if any(s in (StageState.RUNNING, StageState.SUCCEEDED) for s in states):
        return JobState.RUNNING
    return JobState.QUEUED


def rows_to_rerun(
    kind: str, rows: Iterable[StageView], capture_key: str, params: Mapping[str, Any]
) -> set[str]:
    """The rows a retry with ``params`` re-runs: those not succeeded, those whose key under
    ``params`` differs from the output they hold (new parameters, a new stage version), and
    everything downstream of either. ``rows`` in graph order, so upstream keys come first."""
    rerun: set[str] = set()
    keys: dict[str, str] = {}
    for st in rows:
        upstream = {d: keys.get(d, "") for d in st.depends_on}
        keys[st.name] = row_key(kind, st.name, capture_key, params, upstream)
        changed = st.output_key != keys[st.name]
        if st.state != StageState.SUCCEEDED or changed or any(d in rerun for d in st.depends_on):
            rerun.add(st.name)
    return rerun
