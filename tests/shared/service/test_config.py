"""Configuration: every variable has a default, and a bad value names the variable."""

from __future__ import annotations

from pathlib import Path

import pytest

from shared.core.errors import InputError
from shared.service.config import DEFAULT_BROKER_URL, get_settings


def test_defaults_run_on_one_machine(tmp_path: Path) -> None:
    s = get_settings({"GRAYLIGHT_DATA_DIR": str(tmp_path)})
    assert s.database_url == f"sqlite:///{tmp_path / 'graylight.db'}"
    assert s.storage_url == str(tmp_path / "artifacts") and s.broker_url == DEFAULT_BROKER_URL
    assert s.queue("cpu") == "cpu" and s.cache_dir == tmp_path / "cache"
    prefixed = get_settings({"GRAYLIGHT_DATA_DIR": str(tmp_path), "GRAYLIGHT_QUEUE_PREFIX": "museum-"})
    assert prefixed.queue("render") == "museum-render"


def test_signing_secret_is_kept(tmp_path: Path) -> None:
    s = get_settings({"GRAYLIGHT_DATA_DIR": str(tmp_path)})
    first = s.signing_secret()
    assert len(first) == 64 and s.signing_secret() == first
    assert (tmp_path / "secret").stat().st_mode & 0o777 == 0o600
    assert get_settings({"GRAYLIGHT_DATA_DIR": str(tmp_path), "GRAYLIGHT_SECRET": "k"}).signing_secret() == b"k"


@pytest.mark.parametrize(
    ("name", "value", "message"),
    [
        ("GRAYLIGHT_LEASE_SECONDS", "soon", "must be a number"),
        ("GRAYLIGHT_MAX_ATTEMPTS", "0", "must be at least 1"),
        ("GRAYLIGHT_MAX_UPLOAD_BYTES", "1.5", "must be an integer"),
        ("GRAYLIGHT_RERENDER_HOUR", "24", "must be an hour 0..23"),
        ("GRAYLIGHT_RERENDER_MODE", "sometimes", 'must be "changed" or "all"'),
    ],
)
def test_bad_values_name_the_variable(tmp_path: Path, name: str, value: str, message: str) -> None:
    with pytest.raises(InputError) as err:
        get_settings({"GRAYLIGHT_DATA_DIR": str(tmp_path), name: value})
    assert str(err.value).startswith(f"{name}: ") and message in str(err.value)
