"""The broker contract: configuration that loses no work, and the publisher, on the real Redis."""

from __future__ import annotations

import json
import uuid
from pathlib import Path

import redis

from shared.service.config import get_settings
from shared.service.jobs import longest_time_limit
from shared.service.jobstore import Stage
from shared.service.queue import celery_config, publish_stages, task_name


def _stage(stage_id: int, name: str, queue: str) -> Stage:
    return Stage(id=stage_id, job_id="j", name=name, position=0, queue=queue, depends_on=(), state="queued",
                 attempts=0, progress=0.0, input_key=None, output_key=None, lease_token=None, lease_owner=None,
                 heartbeat_at=None, queued_at=None, started_at=None, finished_at=None, error=None, summary=None,
                 reused=False)  # fmt: skip


def test_visibility_timeout_exceeds_every_stage(tmp_path: Path) -> None:
    conf = celery_config(get_settings({"GRAYLIGHT_DATA_DIR": str(tmp_path)}))
    assert conf["broker_transport_options"]["visibility_timeout"] > longest_time_limit()
    assert conf["task_acks_late"] and conf["worker_prefetch_multiplier"] == 1
    assert conf["result_backend_transport_options"] == conf["broker_transport_options"]


def test_publisher_sends_one_message_per_stage_to_its_queue(tmp_path: Path) -> None:
    prefix = f"t{uuid.uuid4().hex[:8]}-"
    settings = get_settings({"GRAYLIGHT_DATA_DIR": str(tmp_path), "GRAYLIGHT_QUEUE_PREFIX": prefix})
    stages = [_stage(7, "decode", "cpu"), _stage(8, "tiles_chunk#2", "render")]
    client = redis.Redis.from_url(settings.broker_url)
    try:
        assert publish_stages(stages, settings) == 2
        cpu = [json.loads(m) for m in client.lrange(f"{prefix}cpu", 0, -1)]
        render = [json.loads(m) for m in client.lrange(f"{prefix}render", 0, -1)]
        assert [m["headers"]["task"] for m in cpu] == [task_name("decode")]
        assert [m["headers"]["task"] for m in render] == ["graylight.stage.tiles_chunk"]
    finally:
        client.delete(f"{prefix}cpu", f"{prefix}render")


def test_publish_with_the_broker_down_is_logged_not_raised(tmp_path: Path) -> None:
    settings = get_settings({"GRAYLIGHT_DATA_DIR": str(tmp_path), "GRAYLIGHT_BROKER_URL": "redis://127.0.0.1:1/0"})
    assert publish_stages([_stage(1, "decode", "cpu")], settings) == 0
