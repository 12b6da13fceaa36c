"""The worker's Celery app: one task per stage, plus the reconciler and the nightly re-render.

Built here and only here, from :func:`shared.service.queue.celery_config` (the broker
contract the publisher shares): per-stage hard and soft time limits from the job graph;
retries with exponential backoff and jitter for transient faults only;
``worker_max_memory_per_child`` replaces a child that grew too big; separate ``cpu``,
``render`` and ``control`` queues. Nothing but the command line (``graylight worker``,
``graylight beat``) and ``celery -A workers.celery_app`` imports this module: the API
publishes through :mod:`shared.service.queue` without it.
"""

from __future__ import annotations

import logging
import threading
from typing import Any

from celery import Celery
from celery.signals import worker_process_init

from shared.service.config import Settings, get_settings
from shared.service.jobs import all_stage_specs
from shared.service.jobstore import dispose_engines
from shared.service.queue import (
    RECONCILE_TASK,
    RERENDER_PREVIEW_TASK,
    RERENDER_TASK,
    celery_config,
    task_name,
)
from workers.reconciler import reconcile_once
from workers.rerender import enqueue_rerenders, run_rerender
from workers.runner import TRANSIENT, run_stage
from workers.warmup import load_kernels_in_background

log = logging.getLogger(__name__)

_APPS: dict[tuple[str, str, str, str], Celery] = {}
_APPS_LOCK = threading.Lock()


def make_app(settings: Settings) -> Celery:
    """A Celery app for ``settings`` with the stage, reconcile and re-render tasks."""
    app = Celery("graylight", set_as_current=False)
    app.conf.update(celery_config(settings))
    app.graylight_settings = settings  # type: ignore[attr-defined]

    for name, spec in all_stage_specs().items():

        def stage_task(self: Any, stage_id: int) -> str:
            retries_left = self.request.retries < self.max_retries
            return run_stage(int(stage_id), settings, retries_left=retries_left).status

        # shared=False: a shared task would be added to every Celery app finalized later in
        # this process (another settings' app, the publisher), running with *these* settings.
        app.task(
            stage_task,
            name=task_name(name),
            shared=False,
            bind=True,
            time_limit=spec.time_limit,
            soft_time_limit=int(spec.time_limit * 0.9),
            autoretry_for=TRANSIENT,
            retry_backoff=2,
            retry_backoff_max=120,
            retry_jitter=True,
            max_retries=4,
        )

    def reconcile_task() -> dict[str, int]:
        return reconcile_once(settings).as_dict()

    def rerender_task(mode: str = "changed") -> int:
        # The mode comes in the message from beat (its GRAYLIGHT_RERENDER_MODE): the worker's
        # own environment does not decide it.
        return enqueue_rerenders(settings, mode)

    def rerender_preview_task(rerender_id: str) -> str:
        return run_rerender(str(rerender_id), settings)

    app.task(reconcile_task, name=RECONCILE_TASK, time_limit=300, shared=False)
    app.task(rerender_task, name=RERENDER_TASK, time_limit=3600, shared=False)
    preview = all_stage_specs()["preview"]
    app.task(rerender_preview_task, name=RERENDER_PREVIEW_TASK, shared=False,
             time_limit=preview.time_limit, soft_time_limit=int(preview.time_limit * 0.9),
             autoretry_for=TRANSIENT, retry_backoff=2, retry_backoff_max=120, retry_jitter=True, max_retries=4)  # fmt: skip
    return app


def get_app(settings: Settings | None = None) -> Celery:
    """The (cached) app for ``settings`` (default: the environment's)."""
    settings = settings or get_settings()
    k = (settings.broker_url, settings.queue_prefix, settings.database_url, settings.storage_url)
    with _APPS_LOCK:
        if k not in _APPS:
            _APPS[k] = make_app(settings)
        return _APPS[k]


@worker_process_init.connect
def _after_fork(**_kwargs: Any) -> None:
    # A forked child must not share the parent's pooled database connections.
    dispose_engines()
    # Load the stages' compiled numba kernels now, not inside the first job.
    load_kernels_in_background()


#: The app ``celery -A workers.celery_app`` and ``graylight worker`` use.
app = get_app()
