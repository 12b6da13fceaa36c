"""The deploy files parse, name every service the issue asks for, run exactly one beat, and
document every setting ``shared.service.config`` reads."""

from __future__ import annotations

import re
from pathlib import Path

import yaml

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"


def test_compose_and_k8s_cover_every_service() -> None:
    compose = yaml.safe_load((DEPLOY / "compose.yaml").read_text())
    services = compose["services"]
    assert {"api", "worker-cpu", "worker-render", "beat", "redis", "postgres", "minio"} <= set(services)
    assert "--queues" in services["worker-render"]["command"] and "render" in services["worker-render"]["command"]
    docs = [d for f in sorted((DEPLOY / "k8s").glob("*.yaml")) for d in yaml.safe_load_all(f.read_text()) if d]
    names = {d["metadata"]["name"] for d in docs}
    assert {"graylight-api", "graylight-worker-cpu", "graylight-worker-render", "graylight-beat",
            "redis", "postgres", "minio"} <= names  # fmt: skip
    beat = next(d for d in docs if d["metadata"]["name"] == "graylight-beat")
    assert beat["spec"]["replicas"] == 1 and beat["spec"]["strategy"]["type"] == "Recreate"


def test_every_setting_is_documented() -> None:
    source = (Path(__file__).resolve().parents[2] / "shared" / "service" / "config.py").read_text()
    read = set(re.findall(r'"(GRAYLIGHT_[A-Z0-9_]+)"', source))
    readme = (DEPLOY / "README.md").read_text()
    missing = sorted(v for v in read if v not in readme)
    assert len(read) > 15 and not missing, missing
