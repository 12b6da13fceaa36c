"""The import contracts of ``.importlinter`` hold, and the checker does catch a wrong-way import."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
LINT = Path(sys.executable).with_name("lint-imports")


def _lint(root: Path) -> subprocess.CompletedProcess[str]:
    # PYTHONPATH=root so grimp finds the packages of *that* tree, not the installed ones.
    return subprocess.run(
        [str(LINT), "--config", str(root / ".importlinter"), "--no-cache"],
        cwd=root, capture_output=True, text=True, env={"PYTHONPATH": str(root), "PATH": "/usr/bin:/bin"},
        timeout=300,
    )  # fmt: skip


def test_import_contracts_hold() -> None:
    res = _lint(REPO)
    assert res.returncode == 0, res.stdout[-4000:] + res.stderr[-2000:]
    assert "0 broken" in res.stdout


def _copy_tree(dst: Path) -> None:
    shutil.copy(REPO / ".importlinter", dst / ".importlinter")
    for pkg in ("shared", "workers", "services"):
        for src in (REPO / pkg).rglob("*.py"):
            if "node_modules" in src.parts:
                continue
            out = dst / src.relative_to(REPO)
            out.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(src, out)


@pytest.mark.parametrize(
    ("module", "line", "contract"),
    [
        ("shared/scan/decode.py", "from shared.service.jobstore import JobStore", "Layers"),
        ("shared/formats/ply.py", "from shared.render.octree import build_tiles", "Layers"),
        ("services/api/app.py", "import workers.runner", "reach the workers only through the broker"),
        ("shared/render/raster.py", "import sqlalchemy", "never imports the job store"),
    ],
)
def test_a_wrong_way_import_breaks_a_contract(tmp_path: Path, module: str, line: str, contract: str) -> None:
    _copy_tree(tmp_path)
    target = tmp_path / module
    # Inside a function, where a circle would hide from a naive check: it still counts.
    target.write_text(target.read_text() + f"\n\ndef _wrong_way():\n    {line}\n")
    res = _lint(tmp_path)
    assert res.returncode != 0, res.stdout[-3000:]
    flat = " ".join(res.stdout.split())  # contract names wrap across lines
    named = flat.index(contract)
    assert flat.find("BROKEN", named) != -1 and flat.find("KEPT", named, flat.find("BROKEN", named)) == -1, flat[-3000:]
