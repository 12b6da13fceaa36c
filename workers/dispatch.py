"""Publishing stage messages: a message carries a stage id, nothing else.

A failed publish (broker down) is logged, not raised: the stage is ``queued`` in the
database, and the reconciler publishes it again once the broker answers.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable

from shared.service.config import Settings
from shared.service.jobstore import Stage

log = logging.getLogger(__name__)


def task_name(stage: str) -> str:
    """The Celery task that runs stage ``stage`` (a map stage's rows share their spec's task)."""
    from shared.service.jobs import base_name

    return f"graylight.stage.{base_name(stage)}"


def publish_stages(stages: Iterable[Stage], settings: Settings) -> int:
    """Send one message per stage to its queue; returns how many were sent."""
    from workers.celery_app import get_app

    app = get_app(settings)
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
