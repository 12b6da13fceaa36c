"""Lazy public APIs for the domain packages (PEP 562).

A package ``__init__`` names what it exports and where each name lives; the module holding a
name is imported on first use, so ``import shared.scan`` does not pay for numba or OpenCV
until a kernel is needed (``graylight --help`` stays fast).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from typing import Any

__all__ = ["lazy_exports"]


def lazy_exports(
    package: str, exports: Mapping[str, str]
) -> tuple[list[str], Callable[[str], Any], Callable[[], list[str]]]:
    """``(__all__, __getattr__, __dir__)`` for ``package`` whose public ``exports`` map each
    name to its submodule (``{"decode_capture": "decode"}``)."""

    def __getattr__(name: str) -> Any:
        module = exports.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f"{package}.{module}"), name)
        globals_of_package = importlib.import_module(package).__dict__
        globals_of_package[name] = value  # later look-ups skip this function
        return value

    def __dir__() -> list[str]:
        return sorted(set(exports) | set(importlib.import_module(package).__dict__))

    return sorted(exports), __getattr__, __dir__
