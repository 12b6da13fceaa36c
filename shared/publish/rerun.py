"""Re-running a recorded run: what to check before (the inputs are the ones recorded) and after
(the outputs are the ones recorded, sha256 for sha256).

The command itself is repeated by the caller (``graylight rerun``, which owns the command line);
this module only reads paradata and files.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from shared.core.errors import InputError
from shared.publish.paradata import main_activity, normalised_json_sha256, sha256_file, software

__all__ = ["OutputCheck", "check_inputs", "compare_outputs", "recorded_outputs", "software_differences"]


@dataclass(frozen=True)
class OutputCheck:
    """One recorded output against its re-made file: ``status`` is ``equal``, ``differs`` or ``missing``."""

    path: str
    recorded_sha256: str
    new_sha256: str | None
    volatile: bool
    #: For a record with timings: whether it is equal with timings and output paths left out.
    equal_normalised: bool | None = None

    @property
    def status(self) -> str:
        if self.new_sha256 is None:
            return "missing"
        if self.new_sha256 == self.recorded_sha256:
            return "equal"
        return "equal-normalised" if self.equal_normalised else "differs"


def _nodes(doc: dict[str, Any]) -> dict[str, dict[str, Any]]:
    return {n["@id"]: n for n in doc["@graph"]}


def check_inputs(doc: dict[str, Any], where: Path) -> list[dict[str, Any]]:
    """The input entities of the recorded run, each checked to exist at its recorded place with its
    recorded sha256: :class:`InputError` naming the first that does not (a re-run from other inputs
    would not reproduce anything)."""
    act = main_activity(doc, where)
    nodes = _nodes(doc)
    out = []
    for ident in act.get("used", []):
        ent = nodes.get(ident)
        if ent is None:
            raise InputError(where, f"used: {ident} is not in the graph")
        loc = Path(str(ent.get("atLocation", "")))
        if not loc.is_file():
            raise InputError(loc, "input of the recorded run is missing")
        if sha256_file(loc) != ent.get("sha256"):
            raise InputError(loc, "input changed since the recorded run (sha256 differs)")
        out.append(ent)
    return out


def recorded_outputs(doc: dict[str, Any]) -> list[dict[str, Any]]:
    """The output entities of the recorded run."""
    run = doc["run"]
    return [n for n in doc["@graph"] if n.get("wasGeneratedBy") == run]


def compare_outputs(doc: dict[str, Any], new_root: Path) -> list[OutputCheck]:
    """Each recorded output (by its path relative to the run's output) against the file under ``new_root``."""
    checks = []
    for ent in recorded_outputs(doc):
        rel = str(ent.get("path", ""))
        f = new_root / rel
        inside = f.resolve().is_relative_to(new_root.resolve())
        present = inside and f.is_file()
        norm = None
        if present and ent.get("sha256Normalised"):
            norm = normalised_json_sha256(f, new_root) == ent["sha256Normalised"]
        checks.append(OutputCheck(rel, str(ent.get("sha256")), sha256_file(f) if present else None,
                                  bool(ent.get("volatile")), norm))
    return checks


def software_differences(doc: dict[str, Any]) -> list[str]:
    """How the software now differs from the recorded run's (version, git revision, libraries): a
    re-run is bit-for-bit only with the same software."""
    act = main_activity(doc)
    agent = _nodes(doc).get(act.get("wasAssociatedWith"), {})
    now = software()
    diffs = []
    for key in ("version", "gitRevision"):
        if agent.get(key) != now.get(key):
            diffs.append(f"Graylight {key} {agent.get(key)} then, {now.get(key)} now")
    then_libs, now_libs = agent.get("libraries", {}) or {}, now["libraries"]
    for name in sorted(set(then_libs) | set(now_libs)):
        if then_libs.get(name) != now_libs.get(name):
            diffs.append(f"{name} {then_libs.get(name)} then, {now_libs.get(name)} now")
    return diffs
