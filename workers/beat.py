"""The beat process: the reconciler's schedule and the nightly re-render, run exactly once.

:func:`hold_beat_lock` takes a lock in Redis (renewed by a thread; it expires when the beat
dies) or refuses to start, so a second beat for the same queues cannot double the schedule.
"""

from __future__ import annotations

import atexit
import logging
import os
import secrets
import threading
import time

import redis
from celery.apps.beat import Beat

from shared.core.errors import GraylightError
from shared.service.config import Settings
from workers.celery_app import get_app

log = logging.getLogger(__name__)

#: Seconds a beat's lock lives without renewal (a dead beat frees it this fast).
BEAT_LOCK_TTL = 30


class BeatLockError(GraylightError):
    """Another beat holds the lock, or the broker cannot be reached to take it."""


def beat_lock_name(settings: Settings) -> str:
    """The Redis key of the beat lock for ``settings``' queues."""
    return f"{settings.queue_prefix}graylight-beat-lock"


def hold_beat_lock(settings: Settings) -> None:
    """Make sure this is the only beat of its queues, or raise :class:`BeatLockError`.
    Only a Redis broker is checked."""
    if not settings.broker_url.startswith(("redis://", "rediss://")):
        return
    name = beat_lock_name(settings)
    token = secrets.token_hex(8)
    client = redis.Redis.from_url(settings.broker_url, socket_timeout=5, socket_connect_timeout=5)
    try:
        got = client.set(name, token, nx=True, ex=BEAT_LOCK_TTL)
    except redis.exceptions.ConnectionError as exc:
        raise BeatLockError(f"beat: cannot reach the broker at {settings.broker_url}: {exc}") from None
    if not got:
        raise BeatLockError(f"another beat already runs for these queues (Redis key {name!r}); run exactly one")

    def renew() -> None:
        while True:
            time.sleep(BEAT_LOCK_TTL / 3)
            try:
                held = client.get(name)
                if held is None:
                    # Redis restarted (keys gone): take the lock back unless another beat did.
                    if not client.set(name, token, nx=True, ex=BEAT_LOCK_TTL):
                        log.critical("another beat took the lock; stopping this one")
                        os._exit(3)
                elif held.decode() != token:
                    log.critical("another beat holds the lock; stopping this one")
                    os._exit(3)
                else:
                    client.expire(name, BEAT_LOCK_TTL)
            except redis.exceptions.RedisError as exc:  # the broker blinks; beat itself retries too
                log.warning("beat lock: %s", exc)

    def release() -> None:
        # Free the lock at a clean exit so a replacement need not wait for it to expire.
        try:
            if client.get(name) == token.encode():
                client.delete(name)
        except redis.exceptions.RedisError:
            pass

    atexit.register(release)
    threading.Thread(target=renew, name="beat-lock", daemon=True).start()


def run_beat(settings: Settings, loglevel: str = "info") -> None:
    """Take the lock, then run Celery beat in this process until it is stopped."""
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    hold_beat_lock(settings)
    app = get_app(settings)
    Beat(app=app, loglevel=loglevel, schedule=app.conf.beat_schedule_filename).run()
