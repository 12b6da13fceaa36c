"""``graylight publish`` and ``graylight rerun``.

* ``publish OUTPUT_DIR --out DIR [--title T] [--collection C] [--identifier I]``: a museum's folder from a
  ``graylight merge`` or ``graylight scan`` output: ``scene.svx.json`` (Smithsonian Voyager) with the
  model's derivatives, ``paradata.json``, ``qa.json`` and ``qa.html`` (:mod:`shared.publish.folder`).
* ``rerun PARADATA.json --out DIR``: repeat the run a paradata document records, from the same inputs
  (checked by sha256 first) with the same parameters, into DIR, and compare every output with the
  recorded one. Exit 0 when every output that is not a timing record is identical, bit for bit.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from shared.core.errors import InputError

log = logging.getLogger(__name__)

# Parameters of a calibration that name extra output files; a re-run writes them into DIR too.
_EXTRA_OUTPUTS = ("report", "plot", "export_opencv")


def _cmd_rerun(args: argparse.Namespace) -> int:
    from services.cli.main import build_parser, main
    from services.cli.provenance import RECORDED, argv_for
    from shared.publish.paradata import load_paradata, main_activity
    from shared.publish.rerun import check_inputs, compare_outputs, software_differences

    source = Path(args.paradata)
    doc = load_paradata(source)
    act = main_activity(doc, source)
    stage = act.get("stage")
    if stage not in RECORDED or stage in ("rerun",):
        raise InputError(source, f"stage: {stage!r} is not a command graylight rerun can repeat")
    params = dict(act.get("parameters") or {})
    if not isinstance(params.get("out"), str):
        raise InputError(source, "parameters.out: missing")
    check_inputs(doc, source)
    for line in software_differences(doc):
        log.warning("software differs from the recorded run: %s", line)
    out = Path(args.out).resolve()
    if RECORDED[stage].out_is_dir:
        params["out"] = str(out)
        new_root = out
    else:
        out.mkdir(parents=True, exist_ok=True)
        params["out"] = str(out / Path(params["out"]).name)
        for dest in _EXTRA_OUTPUTS:
            if isinstance(params.get(dest), str):
                params[dest] = str(out / Path(params[dest]).name)
        new_root = out
    if Path(params["out"]).resolve() == Path(str(main_activity(doc).get("parameters", {}).get("out"))).resolve():
        raise InputError("--out", "is where the recorded run wrote: re-run into another folder")
    params.pop("command", None)
    argv = argv_for(build_parser([stage]), stage, params)
    log.info("re-running: graylight %s", " ".join(argv))
    code = main(argv)
    if code != 0:
        return code
    checks = compare_outputs(doc, new_root)
    # A record of timings must match with its timings left out; a record that is not JSON is not compared.
    bad = [c for c in checks if c.status == "missing" or (c.status == "differs" and
                                                          (not c.volatile or c.equal_normalised is False))]
    for c in checks:
        note = {"equal-normalised": " (the same with timings and output paths left out)"}.get(c.status, "")
        if c.status == "differs" and c not in bad:
            note = " (a record of timings: not compared)"
        print(f"{c.status:<16} {c.path}{note}")
    if bad:
        raise InputError(source, f"{len(bad)} of {len(checks)} outputs not reproduced: "
                                 + ", ".join(f"{c.path} {c.status}" for c in bad[:5]))
    same = sum(c.status == "equal" for c in checks)
    print(f"reproduced: {same} of {len(checks)} outputs identical (sha256), "
          f"{sum(c.status == 'equal-normalised' for c in checks)} records equal but for timings")
    return 0


def _cmd_publish(args: argparse.Namespace) -> int:
    from shared.publish.folder import ObjectMeta, publish_folder

    source = Path(args.source)
    meta = ObjectMeta(title=args.title if args.title is not None else source.resolve().name,
                      collection=args.collection or "", identifier=args.identifier if args.identifier is not None
                      else source.resolve().name)
    qa = publish_folder(source, Path(args.out), meta)
    out = Path(args.out)
    print(qa["verdict"]["line"])
    levels = ", ".join(f"{d['quality']} {d['file']}" for d in qa["derivatives"])
    print(f"scene:    {out / 'scene.svx.json'} ({levels})")
    print(f"report:   {out / 'qa.html'} ({out / 'qa.json'})")
    print(f"paradata: {out / 'paradata.json'}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("publish", help="a Voyager scene, paradata and quality report from a merge or scan output",
                              description="Write a folder a museum can put on its web server: scene.svx.json "
                                          "(Smithsonian Voyager) with the model's derivatives, paradata.json, "
                                          "qa.json and qa.html, from a graylight merge or scan output folder.")
    p.add_argument("source", help="a graylight merge or scan output folder")
    p.add_argument("--out", required=True, help="folder to write (must not exist or be empty)")
    p.add_argument("--title", help="the object's title (default: the source folder's name)")
    p.add_argument("--collection", help="the collection it belongs to")
    p.add_argument("--identifier", help="its identifier in the collection (default: the source folder's name)")
    p.set_defaults(func=_cmd_publish)

    p = subparsers.add_parser("rerun", help="repeat a recorded run from its paradata.json and compare the outputs",
                              description="Repeat the run a paradata.json records, from the same inputs, into "
                                          "another folder; compare every output's sha256 with the recorded one.")
    p.add_argument("paradata", help="paradata.json (or <file>.paradata.json) of the run")
    p.add_argument("--out", required=True, help="folder for the re-made outputs")
    p.set_defaults(func=_cmd_rerun)


__all__ = ["register"]

if __name__ == "__main__":  # pragma: no cover
    from services.cli.main import main

    sys.exit(main())
