"""The job service's tiles stages with ``params.tiles.node_codec``: plan, one task a chunk,
merge and the preview after them, through the stage adapters (workers.stages)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from shared.core.errors import InputError
from tests.support.clouds import synthetic_scan


def _run_tiles(tmp_path: Path, params: dict) -> tuple[Path, dict]:
    from shared.service.jobs import FANOUT_SEP
    from workers.stages import STAGE_FUNCS, StageContext

    tri = tmp_path / "triangulate"
    tri.mkdir()
    synthetic_scan(tri / "cloud.ply", 30_000, seed=4)

    def ctx(stage: str, inputs: dict[str, Path], index: int | None = None) -> StageContext:
        out = tmp_path / stage.replace(FANOUT_SEP, "_")
        out.mkdir()
        return StageContext(job_id="j", kind="scan", stage=stage, params=params, capture_dir=None,
                            inputs=inputs, out_dir=out, index=index)  # fmt: skip

    plan = ctx("tiles_plan", {"triangulate": tri})
    fanout = STAGE_FUNCS["tiles_plan"](plan)["fanout"]
    assert fanout > 1
    chunks = {}
    for i in range(fanout):
        c = ctx(f"tiles_chunk{FANOUT_SEP}{i}", {"tiles_plan": plan.out_dir}, index=i)
        STAGE_FUNCS["tiles_chunk"](c)
        chunks[c.stage] = c.out_dir
    (tmp_path / "tiles_root").mkdir()
    merge = ctx("tiles_root/tiles", {"tiles_plan": plan.out_dir, **chunks})
    STAGE_FUNCS["tiles"](merge)
    preview = ctx("preview", {"tiles": merge.out_dir})
    summary = STAGE_FUNCS["preview"](preview)
    return merge.out_dir, summary


def test_octree_node_codec_through_the_stage_adapters(tmp_path: Path) -> None:
    params = {"tiles": {"node_codec": "octree", "max_chunk": 8000, "max_leaf": 1000},
              "preview": {"size": [96, 64], "seconds": 0.2, "fps": 10}}  # fmt: skip
    tiles, preview = _run_tiles(tmp_path, params)
    meta = json.loads((tiles / "metadata.json").read_text())
    assert meta["encoding"] == "GRAYLIGHT_OCTREE" and meta["points"] > 20_000
    assert (tiles / "octree.bin").stat().st_size < meta["points"] * 34 / 2
    assert preview["frames"] == 2 and (tmp_path / "preview" / "preview.mp4").stat().st_size > 0


def test_a_bad_node_codec_is_refused_at_intake() -> None:
    from shared.service.params import check_job_params

    with pytest.raises(InputError, match=r"params\.tiles\.node_codec"):
        check_job_params("scan", {"tiles": {"node_codec": "gzip"}})
