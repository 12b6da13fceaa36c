"""The Celery app: broker settings chosen so that no work is lost, and one task per stage.

* ``task_acks_late`` + ``worker_prefetch_multiplier=1``: a message is acknowledged only
  after its stage ran, and a worker holds one message per process.
* ``visibility_timeout`` above the longest stage's time limit, in the broker's and the
  result backend's transport options alike, so Redis never re-delivers a running stage.
  (No result backend is used: the database is the source of truth for job state.)
* Per-stage hard and soft time limits from the job graph; retries with exponential backoff
  and jitter for transient faults only; ``worker_max_memory_per_child`` replaces a child
  that grew too big; separate ``cpu``, ``render`` and ``control`` queues.
* A killed child's message may be acknowledged anyway (``task_reject_on_worker_lost`` stays
  off: it can loop messages): the reconciler notices the expired lease and re-queues.
* Beat runs the reconciler every ``GRAYLIGHT_RECONCILE_SECONDS`` and the nightly preview
  re-render. Run exactly one beat.
"""

from __future__ import annotations

import logging
import threading
from typing import Any

from celery import Celery
from celery.schedules import crontab
from celery.signals import worker_process_init

from shared.service.config import Settings, get_settings
from shared.service.jobs import all_stage_specs, longest_time_limit
from workers.dispatch import task_name

log = logging.getLogger(__name__)

_APPS: dict[tuple[str, str, str, str], Celery] = {}
_APPS_LOCK = threading.Lock()


def celery_config(settings: Settings) -> dict[str, Any]:
    """The Celery configuration for ``settings``."""
    visibility = int(longest_time_limit() * 1.5) + 300
    control = settings.queue("control")
    return {
        "broker_url": settings.broker_url,
        "broker_transport_options": {"visibility_timeout": visibility},
        "result_backend": None,
        "result_backend_transport_options": {"visibility_timeout": visibility},
        "task_ignore_result": True,
        "task_acks_late": True,
        "task_acks_on_failure_or_timeout": True,
        "task_reject_on_worker_lost": False,
        "worker_prefetch_multiplier": 1,
        "worker_max_memory_per_child": settings.worker_max_memory_mb * 1024,  # KiB
        "worker_cancel_long_running_tasks_on_connection_loss": False,
        "worker_hijack_root_logger": False,
        "worker_send_task_events": False,
        "task_default_queue": settings.queue("cpu"),
        "task_create_missing_queues": True,
        "task_serializer": "json",
        "accept_content": ["json"],
        "broker_connection_retry_on_startup": True,
        "broker_connection_max_retries": None,
        "broker_connection_timeout": 4,
        "broker_heartbeat": 0,
        # Remote-control and event exchanges named per queue prefix: services sharing a
        # Redis database under different prefixes do not hear each other.
        "control_exchange": f"{settings.queue_prefix}graylight",
        "event_exchange": f"{settings.queue_prefix}graylight.ev",
        "beat_schedule_filename": str(settings.data_dir / f"beat-schedule{settings.queue_prefix}"),
        "beat_max_loop_interval": max(1.0, min(5.0, settings.reconcile_seconds)),
        "beat_schedule": {
            "reconcile": {
                "task": "graylight.reconcile",
                "schedule": settings.reconcile_seconds,
                "options": {"queue": control, "expires": max(settings.reconcile_seconds * 2, 2.0)},
            },
            "nightly-preview-rerender": {
                "task": "graylight.rerender_previews",
                "schedule": crontab(hour=settings.rerender_hour, minute=0),
                "options": {"queue": control},
            },
        },
        "timezone": "UTC",
    }


def make_app(settings: Settings) -> Celery:
    """A Celery app for ``settings`` with the stage, reconcile and re-render tasks."""
    app = Celery("graylight", set_as_current=False)
    app.conf.update(celery_config(settings))
    app.graylight_settings = settings  # type: ignore[attr-defined]
    from workers.runner import TRANSIENT, run_stage

    for name, spec in all_stage_specs().items():

        def stage_task(self: Any, stage_id: int) -> str:
            retries_left = self.request.retries < self.max_retries
            return run_stage(int(stage_id), settings, retries_left=retries_left).status

        app.task(
            stage_task,
            name=task_name(name),
            bind=True,
            queue=settings.queue(spec.queue),
            time_limit=spec.time_limit,
            soft_time_limit=int(spec.time_limit * 0.9),
            autoretry_for=TRANSIENT,
            retry_backoff=2,
            retry_backoff_max=120,
            retry_jitter=True,
            max_retries=4,
        )

    def reconcile_task() -> dict[str, int]:
        from workers.reconciler import reconcile_once

        return reconcile_once(settings).as_dict()

    def rerender_task() -> int:
        from workers.reconciler import enqueue_preview_rerender

        return enqueue_preview_rerender(settings, settings.rerender_mode)

    app.task(reconcile_task, name="graylight.reconcile", queue=settings.queue("control"), time_limit=300)
    app.task(rerender_task, name="graylight.rerender_previews", queue=settings.queue("control"), time_limit=3600)
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
    from shared.service.jobstore import dispose_engines

    dispose_engines()


#: The app ``celery -A workers.celery_app`` and ``graylight worker`` use.
app = get_app()
