"""Every range image of the codec bench's table (``make bench``), through the codec as the bench
codes it: lossless at 0.02 mm exact on every sample, within 0.1 mm on every sample, masks exact,
damaged streams refused (either mode). The virtual rig's 2048x1536 scans of the relief, the bunny, the fandisk
and spot at 1:1, 2:1 and 4:1 sampling are rendered afresh (not the bench's cache, which an older
simulator may have made); the Cyberware dragon scans and the synthetic image as the bench
reads them. The five real captures are checked alike in :mod:`test_range`."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from shared.compress import load_range_npz
from shared.core.datapaths import shared_data_dir
from tests.support.range_checks import bounded_blob, check_damage_refused, lossless_blob
from tests.support.range_images import synthetic_range
from tests.support.range_scenes import BENCH_IMAGES, dragon_range, render_bench_range

#: The bench's quantum and error bound (mm).
Q = 0.02
E = 0.1


def _check(z: np.ndarray) -> None:
    assert np.count_nonzero(~np.isnan(z)) > 30_000
    check_damage_refused(lossless_blob(z, Q))
    check_damage_refused(bounded_blob(z, E), seed=1)


@pytest.mark.slow
@pytest.mark.parametrize("scene, ratio", [(s, r) for _, s, r in BENCH_IMAGES], ids=[n for n, _, _ in BENCH_IMAGES])
def test_virtual_rig_bench_image(scene: str, ratio: int, tmp_path: Path) -> None:
    z = load_range_npz(render_bench_range(scene, ratio, tmp_path / "range.npz")).z
    assert z.shape == (1536, 2048)
    _check(z)


@pytest.mark.slow
@pytest.mark.parametrize("k", [0, 5], ids=["dragon scan 0", "dragon scan 120"])
def test_cyberware_dragon_bench_image(k: int) -> None:
    if not (shared_data_dir() / "stanford-dragon-turntable").is_dir():
        pytest.skip("the shared data's Stanford dragon scans are missing")
    _check(dragon_range(k)[1])


@pytest.mark.slow
def test_synthetic_bench_image() -> None:
    _check(synthetic_range(1536, 2048, 0.2, seed=0))
