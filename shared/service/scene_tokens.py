"""Signed, expiring tokens that let a viewer on another origin read one job's published scene.

Smithsonian Voyager Explorer fetches a scene and its derivatives by plain URL: it cannot send the
``Authorization: Bearer`` header the artifact routes ask for. ``GET /v1/jobs/{id}/scene`` (with the
key) therefore answers a URL whose path carries a token: ``{expires}.{signature}``, where
``expires`` is a Unix time in whole seconds and ``signature`` is the base64url HMAC-SHA256, under
:meth:`shared.service.config.Settings.signing_secret`, of the job id, the owning key's id and the
expiry. The token grants reading that job's publish folder until it expires (and while the
owner's key is not revoked, which the route checks); it cannot be widened to another job or key.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import re
from dataclasses import dataclass

__all__ = ["MAX_TOKEN_SECONDS", "MIN_TOKEN_SECONDS", "SceneGrant", "TokenError", "check_scene_token",
           "sign_scene_token"]

#: Shortest and longest life of a token, in seconds (a minute; a week).
MIN_TOKEN_SECONDS = 60
MAX_TOKEN_SECONDS = 7 * 24 * 3600
_TOKEN = re.compile(r"^([0-9]{1,12})\.([A-Za-z0-9_-]{43})$")


class TokenError(ValueError):
    """A scene token that is malformed, forged, for another job or expired (the message says which)."""


@dataclass(frozen=True)
class SceneGrant:
    """What a valid token grants: read job ``job_id`` of key ``owner_id`` until ``expires`` (Unix s)."""

    job_id: str
    owner_id: int
    expires: int


def _signature(secret: bytes, job_id: str, owner_id: int, expires: int) -> str:
    msg = f"graylight-scene\n{job_id}\n{owner_id}\n{expires}".encode()
    return base64.urlsafe_b64encode(hmac.new(secret, msg, hashlib.sha256).digest()).rstrip(b"=").decode()


def sign_scene_token(secret: bytes, job_id: str, owner_id: int, expires: int) -> str:
    """The token for reading ``job_id``'s scene (owned by key ``owner_id``) until ``expires`` (Unix s)."""
    return f"{int(expires)}.{_signature(secret, job_id, owner_id, int(expires))}"


def check_scene_token(secret: bytes, token: str, job_id: str, owner_id: int, now: float) -> SceneGrant:
    """The grant of ``token`` for ``job_id`` owned by ``owner_id`` at time ``now`` (Unix s);
    :class:`TokenError` when it is malformed, signed for something else or expired."""
    m = _TOKEN.match(token)
    if m is None:
        raise TokenError("scene token is malformed")
    expires = int(m.group(1))
    if not hmac.compare_digest(m.group(2), _signature(secret, job_id, owner_id, expires)):
        raise TokenError("scene token is not valid for this job")
    if now >= expires:
        raise TokenError("scene token has expired (ask GET /v1/jobs/{id}/scene for a new one)")
    return SceneGrant(job_id, owner_id, expires)
