"""Every package's declared public API resolves, and importing a package loads no kernels."""

from __future__ import annotations

import importlib
import subprocess
import sys

import pytest

PACKAGES = ["shared.core", "shared.formats", "shared.scan", "shared.calib", "shared.sim", "shared.render",
            "shared.service", "shared.merge", "shared.compress"]  # fmt: skip


@pytest.mark.parametrize("name", PACKAGES)
def test_every_exported_name_resolves(name: str) -> None:
    pkg = importlib.import_module(name)
    assert pkg.__all__, f"{name} declares no public API"
    for attr in pkg.__all__:
        assert getattr(pkg, attr) is not None, f"{name}.{attr}"


def test_importing_the_packages_loads_no_numba() -> None:
    code = "import sys\n" + "".join(f"import {p}\n" for p in PACKAGES) + "print('numba' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
