"""Prometheus metrics of the job service, computed from the database (and the broker) when
Prometheus scrapes, so every API process answers the same whatever the number of workers,
machines or processes: nothing is counted in memory, nothing needs a multi-process directory.

=======================================  =========  ==========================================
metric                                   type       labels
=======================================  =========  ==========================================
``graylight_jobs``                       gauge      ``kind``, ``state``: jobs by kind and state
``graylight_stages``                     gauge      ``queue``, ``state``: stage rows by queue and state
``graylight_stage_duration_seconds``     histogram  ``stage``: run time of succeeded stages (last attempt;
                                                    outputs found in the store are not counted)
``graylight_queue_depth``                gauge      ``queue``: messages waiting on the broker
``graylight_artifact_store_bytes``       gauge      bytes of the objects jobs hold (captures, outputs)
                                                    plus unfinished upload sessions
``graylight_reconciler_repairs_total``   counter    ``repair``: ``lease_expired`` (a stage re-queued
                                                    after its worker vanished), ``worker_lost`` (failed
                                                    after too many lost workers)
=======================================  =========  ==========================================

:class:`ServiceCollector` is a ``prometheus_client`` collector; register it on a registry of its
own (:func:`service_registry`) and serve ``generate_latest(registry)``.
"""

from __future__ import annotations

import bisect
import logging
from collections.abc import Iterator

from prometheus_client import CollectorRegistry
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily, Metric
from prometheus_client.registry import Collector
from sqlalchemy import func, select

from shared.service.artifacts import ArtifactStore
from shared.service.config import Settings
from shared.service.jobs import QUEUES, JobState, StageState, base_name
from shared.service.jobstore import EventRow, JobRow, JobStore, StageRow
from shared.service.usage import ObjectSizes, detached_keys, stored_keys

__all__ = ["DURATION_BUCKETS", "ServiceCollector", "broker_queue_depths", "service_registry"]

log = logging.getLogger(__name__)

#: Upper bounds (seconds) of the stage-duration histogram's buckets: a probe takes
#: milliseconds, a 15 MP decode seconds, a preview of a big cloud many minutes.
DURATION_BUCKETS = (0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 120.0, 300.0, 600.0, 1800.0, 3600.0)


def broker_queue_depths(settings: Settings) -> dict[str, int] | None:
    """Messages waiting on each logical queue of a Redis broker (kombu keeps a queue as a
    list named after it, with priority lists beside it), or None when it cannot be asked."""
    if not settings.broker_url.startswith(("redis://", "rediss://")):
        return None
    try:
        import redis

        client = redis.Redis.from_url(settings.broker_url, socket_timeout=2, socket_connect_timeout=2)
        try:
            out: dict[str, int] = {}
            for q in QUEUES:
                name = settings.queue(q)
                keys = [name, *(f"{name}\x06\x16{p}" for p in range(1, 10))]
                out[q] = sum(int(client.llen(k)) for k in keys)
            return out
        finally:
            client.close()
    except Exception as exc:  # the broker is down: the other metrics still answer
        log.warning("metrics: cannot read queue depths: %s", exc)
        return None


class ServiceCollector(Collector):
    """Collects the metrics of the module docstring at each scrape."""

    def __init__(self, settings: Settings, store: JobStore, arts: ArtifactStore) -> None:
        self.settings = settings
        self.store = store
        self.sizes = ObjectSizes(arts)

    def collect(self) -> Iterator[Metric]:
        with self.store.session() as s:
            jobs = s.execute(select(JobRow.kind, JobRow.state, func.count()).group_by(JobRow.kind, JobRow.state)).all()
            stages = s.execute(
                select(StageRow.queue, StageRow.state, func.count()).group_by(StageRow.queue, StageRow.state)
            ).all()
            runs = s.execute(
                select(StageRow.name, StageRow.finished_at - StageRow.started_at).where(
                    StageRow.state == StageState.SUCCEEDED, StageRow.reused.is_(False),
                    StageRow.started_at.is_not(None), StageRow.finished_at.is_not(None),
                )
            ).all()  # fmt: skip
            expired = s.scalar(
                select(func.count()).select_from(EventRow).where(
                    EventRow.old == StageState.RUNNING, EventRow.new == StageState.QUEUED,
                    EventRow.detail.like("lease of % expired"),
                )
            )  # fmt: skip
            lost = s.scalar(
                select(func.count()).select_from(EventRow).where(
                    EventRow.new == StageState.FAILED, EventRow.detail.like("worker lost %")
                )
            )

        g = GaugeMetricFamily("graylight_jobs", "Jobs by kind and state.", labels=["kind", "state"])
        seen = {(k, st): int(n) for k, st, n in jobs}
        for kind in sorted({k for k, _ in seen}):
            for state in JobState:  # every state, zeros too, so rates and alerts see the series
                g.add_metric([kind, state.value], seen.get((kind, state.value), 0))
        yield g

        g = GaugeMetricFamily("graylight_stages", "Stage rows by queue and state.", labels=["queue", "state"])
        for queue, state, n in sorted(stages):
            g.add_metric([queue, state], int(n))
        yield g

        h = HistogramMetricFamily("graylight_stage_duration_seconds", "Run time of succeeded stages.", labels=["stage"])
        by_stage: dict[str, list[float]] = {}
        for name, seconds in runs:
            by_stage.setdefault(base_name(name), []).append(max(float(seconds or 0.0), 0.0))
        for stage, values in sorted(by_stage.items()):
            values.sort()
            buckets = [(str(b), bisect.bisect_right(values, b)) for b in DURATION_BUCKETS]
            buckets.append(("+Inf", len(values)))
            h.add_metric([stage], buckets, sum_value=sum(values))
        yield h

        depths = broker_queue_depths(self.settings)
        if depths is not None:
            g = GaugeMetricFamily("graylight_queue_depth", "Messages waiting on the broker.", labels=["queue"])
            for q, n in depths.items():
                g.add_metric([q], n)
            yield g

        keys, uploads = stored_keys(self.store)
        yield GaugeMetricFamily("graylight_artifact_store_bytes", "Bytes of stored objects held by jobs, and of uploads.",
                                value=self.sizes.total(keys, deletable=detached_keys(self.store)) + uploads)  # fmt: skip

        c = CounterMetricFamily("graylight_reconciler_repairs", "Repairs made by the reconciler.", labels=["repair"])
        c.add_metric(["lease_expired"], int(expired or 0))
        c.add_metric(["worker_lost"], int(lost or 0))
        yield c


def service_registry(settings: Settings, store: JobStore, arts: ArtifactStore) -> CollectorRegistry:
    """A registry holding only :class:`ServiceCollector` (no process metrics of one API process)."""
    registry = CollectorRegistry(auto_describe=False)
    registry.register(ServiceCollector(settings, store, arts))
    return registry
