"""The one hook that writes paradata for every CLI command that writes outputs.

:func:`run_recorded` runs a parsed command; when the command is one of :data:`RECORDED` and it
succeeds, it writes the run's paradata (:mod:`shared.publish.paradata`): ``paradata.json`` inside
an output folder, ``<file>.paradata.json`` beside an output file. A failed command writes none
(its outputs were never moved into place). ``GRAYLIGHT_PARADATA=0`` turns the hook off.

:func:`argv_for` rebuilds a command line from recorded parameters through the command's own
parser, which is how ``graylight rerun`` repeats a run.
"""

from __future__ import annotations

import argparse
import logging
import os
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

__all__ = ["RECORDED", "Recorded", "argv_for", "outputs_of", "run_recorded"]


@dataclass(frozen=True)
class Recorded:
    """Which parameters of a command name its inputs and its outputs (argparse ``dest`` names);
    ``out_is_dir``: whether ``--out`` is a folder (else a file, with siblings sharing its stem)."""

    inputs: tuple[str, ...]
    outputs: tuple[str, ...] = ("out",)
    out_is_dir: bool = True


RECORDED: dict[str, Recorded] = {
    "scan": Recorded(inputs=("capture", "rig")),
    "merge": Recorded(inputs=("scanset",)),
    "tiles": Recorded(inputs=("cloud",)),
    "preview": Recorded(inputs=("tiles", "path"), out_is_dir=False),
    "compress": Recorded(inputs=("input",), out_is_dir=False),
    "decompress": Recorded(inputs=("file",), out_is_dir=False),
    "export": Recorded(inputs=("cloud",), out_is_dir=False),
    "calibrate": Recorded(inputs=("inputs", "board"), outputs=("out", "report", "plot", "export_opencv"),
                          out_is_dir=False),
    "simulate": Recorded(inputs=()),
    "publish": Recorded(inputs=("source",)),
}


def _paths(value: Any) -> list[Path]:
    """The existing files or folders a parameter names (a keyword such as ``--path auto`` names none)."""
    values = value if isinstance(value, list | tuple) else [value]
    return [Path(v).resolve() for v in values if isinstance(v, str | os.PathLike) and Path(v).exists()]


def outputs_of(spec: Recorded, params: Mapping[str, Any], since_ns: int) -> list[Path]:
    """The files and folders a run wrote: the named outputs, and for a file output the files beside it
    that share its stem and were written during the run (a preview's poster, a calibration's report)."""
    out: list[Path] = []
    for dest in spec.outputs:
        out += _paths(params.get(dest))
    if not spec.out_is_dir and params.get("out"):
        main = Path(params["out"]).resolve()
        if main.is_file():
            for p in sorted(main.parent.glob(f"{main.stem}*")):
                if p.is_file() and p not in out and p.stat().st_mtime_ns >= since_ns \
                        and not p.name.endswith(".paradata.json") and not p.name.startswith("."):
                    out.append(p)
    return out


def run_recorded(args: argparse.Namespace, argv: Sequence[str], func: Callable[[argparse.Namespace], Any]) -> Any:
    """Run ``func(args)``; on success write the paradata of the run when the command writes outputs."""
    spec = RECORDED.get(args.command)
    if spec is None or os.environ.get("GRAYLIGHT_PARADATA", "1") == "0":
        return func(args)
    from shared.publish.paradata import Run, build_paradata, paradata_path_for, write_paradata

    params = {k: v for k, v in vars(args).items() if k not in ("func", "verbose")}
    # Inputs are resolved before the run: a command may write into a folder beside them.
    inputs = {dest: _paths(params.get(dest)) for dest in spec.inputs}
    absolute = _absolute(params, spec)
    started, since = datetime.now(UTC), time.time_ns() - 1_000_000
    result = func(args)
    if int(result or 0) != 0:
        return result
    outputs = outputs_of(spec, params, since)
    if not outputs:
        return result
    main = Path(params["out"]).resolve()
    run = Run(stage=args.command, parameters=absolute, command=list(argv), inputs=inputs,
              outputs={"out": outputs}, started=started, ended=datetime.now(UTC),
              output_root=main if main.is_dir() else main.parent)
    path = paradata_path_for(main)
    if path.is_file() and path.stat().st_mtime_ns >= since:
        return result  # the command brought its own (a job's, downloaded by graylight publish JOB_ID)
    write_paradata(path, build_paradata(run))
    log.info("paradata: %s", path)
    return result


def _absolute(params: Mapping[str, Any], spec: Recorded) -> dict[str, Any]:
    """Parameters with every path-valued input and output made absolute, so a re-run finds them from anywhere."""
    out = dict(params)
    for dest in (*spec.inputs, *spec.outputs):
        v = out.get(dest)
        if isinstance(v, list | tuple):
            out[dest] = [str(Path(x).resolve()) if Path(x).exists() or dest in spec.outputs else x for x in v]
        elif isinstance(v, str | os.PathLike) and (Path(v).exists() or dest in spec.outputs):
            out[dest] = str(Path(v).resolve())
    return out


def argv_for(parser: argparse.ArgumentParser, command: str, params: Mapping[str, Any]) -> list[str]:
    """The command line that parses back to ``params`` with ``command``'s own parser (positionals in
    order, options with their values, flags when set)."""
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))  # noqa: SLF001
    cmd = sub.choices[command]
    argv = [command]
    for action in cmd._actions:  # noqa: SLF001
        if isinstance(action, argparse._HelpAction) or action.dest not in params:  # noqa: SLF001
            continue
        value = params[action.dest]
        if not action.option_strings:
            argv += [str(v) for v in value] if isinstance(value, list) else [str(value)]
        elif isinstance(action, argparse._StoreTrueAction | argparse._StoreFalseAction):  # noqa: SLF001
            if value != action.default:
                argv.append(action.option_strings[0])
        elif isinstance(action, argparse._StoreConstAction):  # noqa: SLF001
            if value == action.const:
                argv.append(action.option_strings[0])
        elif value is not None:  # defaults too: a later version's defaults must not change a re-run
            argv += [action.option_strings[0], *([str(v) for v in value] if isinstance(value, list) else [str(value)])]
    return argv
