"""The broker contract: Celery configuration, task names, queue names, and the publisher.

Both sides of the queue read this module: the API and the reconciler publish stage
messages through :func:`publish_stages`, and the worker app (``workers/celery_app.py``)
registers its tasks under :func:`task_name` with :func:`celery_config`. A message carries
a stage id, nothing else; the database is the source of truth for job state.

* ``task_acks_late`` + ``worker_prefetch_multiplier=1``: a message is acknowledged only
  after its stage ran, and a worker holds one message per process.
* ``visibility_timeout`` above the longest stage's time limit, in the broker's and the
  result backend's transport options alike, so Redis never re-delivers a running stage.
  (No result backend is used.)
* A killed child's message may be acknowledged anyway (``task_reject_on_worker_lost`` stays
  off: it can loop messages): the reconciler notices the expired lease and re-queues.

A failed publish (broker down) is logged, not raised: the stage is ``queued`` in the
database, and the reconciler publishes it again once the broker answers.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterable
from typing import Any

from celery import Celery
from celery.schedules import crontab

from shared.service.config import Settings
from shared.service.jobs import QUEUES, all_stage_specs, base_name, longest_time_limit
from shared.service.jobstore import Stage

log = logging.getLogger(__name__)

__all__ = ["QUEUES", "RECONCILE_TASK", "RERENDER_PREVIEW_TASK", "RERENDER_TASK", "celery_config", "publish_rerender",
           "publish_stages", "publisher", "task_name", "task_routes"]

#: Tasks that are not stages, run from beat on the ``control`` queue.
RECONCILE_TASK = "graylight.reconcile"
RERENDER_TASK = "graylight.rerender_previews"
#: One job's preview re-render (a re-render record's id), on the ``render`` queue.
RERENDER_PREVIEW_TASK = "graylight.rerender_preview"


def task_name(stage: str) -> str:
    """The Celery task that runs stage ``stage`` (a map stage's rows share their spec's task).

    Stable across releases (``graylight.stage.<name>``) so queued messages survive an upgrade."""
    return f"graylight.stage.{base_name(stage)}"


def task_routes(settings: Settings) -> dict[str, dict[str, str]]:
    """Each task's queue: a stage's its spec's, the beat tasks' ``control``, one preview
    re-render's ``render``. In the configuration, not on the tasks: Celery 5.7 deprecates a
    task's own ``queue`` attribute (a warning a task at every registration)."""
    routes = {task_name(name): {"queue": settings.queue(spec.queue)} for name, spec in all_stage_specs().items()}
    control = {"queue": settings.queue("control")}
    routes[RECONCILE_TASK] = control
    routes[RERENDER_TASK] = control
    routes[RERENDER_PREVIEW_TASK] = {"queue": settings.queue("render")}
    return routes


def celery_config(settings: Settings) -> dict[str, Any]:
    """The Celery configuration for ``settings`` (publisher and workers alike)."""
    visibility = int(longest_time_limit() * 1.5) + 300
    control = settings.queue("control")
    return {
        "task_routes": task_routes(settings),
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
                "task": RECONCILE_TASK,
                "schedule": settings.reconcile_seconds,
                "options": {"queue": control, "expires": max(settings.reconcile_seconds * 2, 2.0)},
            },
            # The mode travels with the message: beat's environment is the one place
            # GRAYLIGHT_RERENDER_HOUR and GRAYLIGHT_RERENDER_MODE are read.
            "nightly-preview-rerender": {
                "task": RERENDER_TASK,
                "schedule": crontab(hour=settings.rerender_hour, minute=0),
                "args": [settings.rerender_mode],
                "options": {"queue": control},
            },
        },
        "timezone": "UTC",
    }


def _settings_key(settings: Settings) -> tuple[str, str]:
    return settings.broker_url, settings.queue_prefix


_PUBLISHERS: dict[tuple[str, str], Celery] = {}
_LOCK = threading.Lock()


def publisher(settings: Settings) -> Celery:
    """A (cached) Celery app that only sends messages: no tasks registered, nothing imported
    from the workers, so the API publishes without loading the science."""
    k = _settings_key(settings)
    with _LOCK:
        if k not in _PUBLISHERS:
            app = Celery("graylight-publisher", set_as_current=False)
            app.conf.update(celery_config(settings))
            _PUBLISHERS[k] = app
        return _PUBLISHERS[k]


def publish_stages(stages: Iterable[Stage], settings: Settings) -> int:
    """Send one message per stage to its queue; returns how many were sent."""
    app = publisher(settings)
    sent = 0
    for st in stages:
        try:
            app.send_task(
                task_name(st.name),
                args=[st.id],
                queue=settings.queue(st.queue),
                retry=True,
                retry_policy={"max_retries": 2, "interval_start": 0.1, "interval_step": 0.5, "interval_max": 1.0},
            )
            sent += 1
        except Exception as exc:  # the broker is down: the reconciler re-publishes later
            log.warning("could not publish stage %s (%s) of job %s: %s", st.id, st.name, st.job_id, exc)
    return sent


def publish_rerender(rerender_id: str, settings: Settings) -> bool:
    """Send the message of one preview re-render to the ``render`` queue; False when the broker
    is down (the reconciler publishes it again)."""
    try:
        publisher(settings).send_task(
            RERENDER_PREVIEW_TASK, args=[rerender_id], queue=settings.queue("render"), retry=True,
            retry_policy={"max_retries": 2, "interval_start": 0.1, "interval_step": 0.5, "interval_max": 1.0},
        )  # fmt: skip
        return True
    except Exception as exc:
        log.warning("could not publish re-render %s: %s", rerender_id, exc)
        return False
