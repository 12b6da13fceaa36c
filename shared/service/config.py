"""Configuration of the job service: defaults, overridden by environment variables, in one place.

In: the process environment (``GRAYLIGHT_*`` variables). Out: a frozen :class:`Settings`.
Every variable has a working default, so ``graylight serve``, ``graylight worker`` and
``graylight beat`` run on one machine with nothing set but a running Redis.

========================================  ==============================================
``GRAYLIGHT_DATA_DIR``                    local artifacts, caches and the default SQLite file
``GRAYLIGHT_DATABASE_URL``                SQLAlchemy URL of the job store (SQLite file by default)
``GRAYLIGHT_BROKER_URL``                  Celery broker (``redis://127.0.0.1:6379/0``)
``GRAYLIGHT_STORAGE_URL``                 artifact store: a folder, or ``s3://bucket/prefix``
``GRAYLIGHT_S3_ENDPOINT``                 endpoint of an S3-compatible store (MinIO, moto)
``GRAYLIGHT_API_URL``                     where ``graylight submit`` finds the API
``GRAYLIGHT_API_KEY``                     the key ``graylight submit`` sends
``GRAYLIGHT_QUEUE_PREFIX``                prefix of the queue names (``cpu``, ``render``, ``control``)
``GRAYLIGHT_LEASE_SECONDS``               a running stage whose heartbeat is older has no holder (30)
``GRAYLIGHT_HEARTBEAT_SECONDS``           how often a running stage renews its lease (5)
``GRAYLIGHT_RECONCILE_SECONDS``           period of the reconciler beat task (10)
``GRAYLIGHT_MAX_ATTEMPTS``                claims of one stage before it is failed (5)
``GRAYLIGHT_MAX_UPLOAD_BYTES``            largest accepted upload (8 GiB)
``GRAYLIGHT_UPLOAD_TTL_HOURS``            an upload session not used for a job by then is deleted (24)
``GRAYLIGHT_MAX_ARCHIVE_FILES``           most members in a capture archive (4096)
``GRAYLIGHT_MAX_UNPACKED_BYTES``          largest total unpacked size of an archive (32 GiB)
``GRAYLIGHT_MAX_COMPRESSION_RATIO``       largest unpacked/packed ratio of an archive and of a member (250)
``GRAYLIGHT_MAX_JSON_BYTES``              largest JSON request body, read as it streams (4 MiB)
``GRAYLIGHT_MIN_FREE_BYTES``              ``/health`` answers 503 when the data folder has less free (1 GiB)
``GRAYLIGHT_MAX_IMAGE_PIXELS``            largest image (pixels) accepted in a capture (50 MP)
``GRAYLIGHT_MAX_IMAGE_SIDE``              largest image side accepted in a capture (16384)
``GRAYLIGHT_WORKER_MAX_MEMORY_MB``        a worker child is replaced after it grows past this (4096)
``GRAYLIGHT_RERENDER_HOUR``               UTC hour of the nightly preview re-render (3)
``GRAYLIGHT_RERENDER_MODE``               ``changed`` (default) or ``all``
``GRAYLIGHT_SECRET``                      signs viewer access tokens (default: a file in the data dir)
``GRAYLIGHT_KEY_MAX_RUNNING_JOBS``        jobs one API key may have queued or running at once (0: no limit)
``GRAYLIGHT_KEY_MAX_STORED_BYTES``        bytes one API key's captures, uploads and outputs may fill (0: no limit)
``GRAYLIGHT_LOG_FORMAT``                  ``text`` (default) or ``json``: one JSON object a line, with job and stage ids
========================================  ==============================================
"""

from __future__ import annotations

import os
import secrets
from dataclasses import dataclass, field
from pathlib import Path

from shared.core.errors import InputError

DEFAULT_BROKER_URL = "redis://127.0.0.1:6379/0"
DEFAULT_API_URL = "http://127.0.0.1:8000"


def _default_data_dir() -> Path:
    xdg = os.environ.get("XDG_DATA_HOME")
    base = Path(xdg) if xdg else Path.home() / ".local" / "share"
    return base / "graylight"


def _int(env: dict[str, str], name: str, default: int, minimum: int = 0) -> int:
    raw = env.get(name)
    if raw is None or raw == "":
        return default
    try:
        value = int(raw)
    except ValueError:
        raise InputError(name, f"must be an integer, got {raw!r}") from None
    if value < minimum:
        raise InputError(name, f"must be at least {minimum}, got {value}")
    return value


def _float(env: dict[str, str], name: str, default: float, minimum: float = 0.0) -> float:
    raw = env.get(name)
    if raw is None or raw == "":
        return default
    try:
        value = float(raw)
    except ValueError:
        raise InputError(name, f"must be a number, got {raw!r}") from None
    if not value >= minimum:
        raise InputError(name, f"must be at least {minimum}, got {value}")
    return value


@dataclass(frozen=True)
class Settings:
    """The job service's configuration. Build it with :func:`get_settings`."""

    data_dir: Path
    database_url: str
    broker_url: str
    storage_url: str
    s3_endpoint: str | None
    api_url: str
    api_key: str | None
    queue_prefix: str = ""
    lease_seconds: float = 30.0
    heartbeat_seconds: float = 5.0
    reconcile_seconds: float = 10.0
    max_attempts: int = 5
    max_upload_bytes: int = 8 << 30
    upload_ttl_hours: float = 24.0
    max_archive_files: int = 4096
    max_unpacked_bytes: int = 32 << 30
    max_compression_ratio: int = 250
    max_image_pixels: int = 50_000_000
    max_image_side: int = 16384
    max_json_bytes: int = 4 << 20
    min_free_bytes: int = 1 << 30
    worker_max_memory_mb: int = 4096
    rerender_hour: int = 3
    rerender_mode: str = "changed"
    secret: str | None = field(default=None, repr=False)
    key_max_running_jobs: int = 0
    key_max_stored_bytes: int = 0
    log_format: str = "text"

    def queue(self, name: str) -> str:
        """The broker queue name of a logical queue (``cpu``, ``render`` or ``control``)."""
        return f"{self.queue_prefix}{name}"

    @property
    def cache_dir(self) -> Path:
        """Local cache of fetched artifacts and unpacked captures."""
        return self.data_dir / "cache"

    def signing_secret(self) -> bytes:
        """Secret that signs viewer access tokens: ``GRAYLIGHT_SECRET``, else one kept in the data dir."""
        if self.secret:
            return self.secret.encode()
        path = self.data_dir / "secret"
        if not path.is_file():
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(f".secret.{os.getpid()}.tmp")
            tmp.write_text(secrets.token_hex(32))
            os.chmod(tmp, 0o600)
            # A second process racing here keeps the first file: link fails if it exists.
            try:
                os.link(tmp, path)
            except FileExistsError:
                pass
            finally:
                tmp.unlink(missing_ok=True)
        return path.read_text().strip().encode()


def get_settings(env: dict[str, str] | None = None) -> Settings:
    """Read the configuration from ``env`` (default: ``os.environ``), each variable with its default."""
    env = dict(os.environ if env is None else env)
    data_dir = Path(env.get("GRAYLIGHT_DATA_DIR") or _default_data_dir()).expanduser().absolute()
    database_url = env.get("GRAYLIGHT_DATABASE_URL") or f"sqlite:///{data_dir / 'graylight.db'}"
    storage_url = env.get("GRAYLIGHT_STORAGE_URL") or str(data_dir / "artifacts")
    mode = env.get("GRAYLIGHT_RERENDER_MODE", "changed") or "changed"
    if mode not in ("changed", "all"):
        raise InputError("GRAYLIGHT_RERENDER_MODE", f'must be "changed" or "all", got {mode!r}')
    hour = _int(env, "GRAYLIGHT_RERENDER_HOUR", 3)
    log_format = env.get("GRAYLIGHT_LOG_FORMAT", "text") or "text"
    if log_format not in ("text", "json"):
        raise InputError("GRAYLIGHT_LOG_FORMAT", f'must be "text" or "json", got {log_format!r}')
    if hour > 23:
        raise InputError("GRAYLIGHT_RERENDER_HOUR", f"must be an hour 0..23, got {hour}")
    return Settings(
        data_dir=data_dir,
        database_url=database_url,
        broker_url=env.get("GRAYLIGHT_BROKER_URL") or DEFAULT_BROKER_URL,
        storage_url=storage_url,
        s3_endpoint=env.get("GRAYLIGHT_S3_ENDPOINT") or None,
        api_url=(env.get("GRAYLIGHT_API_URL") or DEFAULT_API_URL).rstrip("/"),
        api_key=env.get("GRAYLIGHT_API_KEY") or None,
        queue_prefix=env.get("GRAYLIGHT_QUEUE_PREFIX", ""),
        lease_seconds=_float(env, "GRAYLIGHT_LEASE_SECONDS", 30.0, 0.1),
        heartbeat_seconds=_float(env, "GRAYLIGHT_HEARTBEAT_SECONDS", 5.0, 0.05),
        reconcile_seconds=_float(env, "GRAYLIGHT_RECONCILE_SECONDS", 10.0, 0.1),
        max_attempts=_int(env, "GRAYLIGHT_MAX_ATTEMPTS", 5, 1),
        max_upload_bytes=_int(env, "GRAYLIGHT_MAX_UPLOAD_BYTES", 8 << 30, 1),
        upload_ttl_hours=_float(env, "GRAYLIGHT_UPLOAD_TTL_HOURS", 24.0, 0.001),
        max_archive_files=_int(env, "GRAYLIGHT_MAX_ARCHIVE_FILES", 4096, 1),
        max_unpacked_bytes=_int(env, "GRAYLIGHT_MAX_UNPACKED_BYTES", 32 << 30, 1),
        max_compression_ratio=_int(env, "GRAYLIGHT_MAX_COMPRESSION_RATIO", 250, 1),
        max_image_pixels=_int(env, "GRAYLIGHT_MAX_IMAGE_PIXELS", 50_000_000, 1),
        max_image_side=_int(env, "GRAYLIGHT_MAX_IMAGE_SIDE", 16384, 1),
        max_json_bytes=_int(env, "GRAYLIGHT_MAX_JSON_BYTES", 4 << 20, 1024),
        min_free_bytes=_int(env, "GRAYLIGHT_MIN_FREE_BYTES", 1 << 30),
        worker_max_memory_mb=_int(env, "GRAYLIGHT_WORKER_MAX_MEMORY_MB", 4096, 64),
        rerender_hour=hour,
        rerender_mode=mode,
        secret=env.get("GRAYLIGHT_SECRET") or None,
        key_max_running_jobs=_int(env, "GRAYLIGHT_KEY_MAX_RUNNING_JOBS", 0),
        key_max_stored_bytes=_int(env, "GRAYLIGHT_KEY_MAX_STORED_BYTES", 0),
        log_format=log_format,
    )
