"""The one confinement rule, as a property over every contract that names a path.

For each contract (a capture's image and rig, a scan set's cloud, capture folder and rig, a job's
preview camera path, a storage reference) and for generated paths of every hostile kind (absolute,
``..``, a link out of the folder to a file, a folder, a device or a FIFO, a FIFO or device inside
the folder): the path is refused at intake with an :class:`InputError` (an ``ArtifactError`` for
the store) that names the field (or, for a FIFO inside the folder, the file); and where the path leads out of the folder, the text is the same
whether its target exists or not.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from shared.core.errors import InputError
from shared.formats.capture import load_capture
from shared.formats.ply import write_ply
from shared.formats.rig import load_rig
from shared.formats.scanset import load_scanset
from shared.render.options import PreviewOptions
from shared.scan.graycode import capture_for_names
from shared.service.artifacts import ArtifactError, ArtifactStore

#: Kinds of hostile path; the first four lead out of the folder (their target may exist or not).
OUTSIDE = ("absolute", "dotdot", "link_file", "link_dir")
KINDS = (*OUTSIDE, "link_device", "link_fifo", "fifo_inside", "device_absolute")

_segment = st.text(alphabet="abcdefghijklmnopqrstuvwxyz0123456789_-", min_size=1, max_size=12)
_names = st.lists(_segment, min_size=1, max_size=3)


def _capture_image(root: Path, value: str) -> None:
    cap = capture_for_names(root, 64, 48)
    doc = cap.to_json()
    doc["white"] = value
    (root / "capture.json").write_text(json.dumps(doc))
    load_capture(root)


def _capture_rig(root: Path, value: str) -> None:
    doc = capture_for_names(root, 64, 48).to_json()
    doc["rig"] = value
    (root / "capture.json").write_text(json.dumps(doc))
    cap = load_capture(root, check=False)
    load_rig(cap.rig)


def _scanset(field: str) -> Callable[[Path, str], None]:
    def attempt(root: Path, value: str) -> None:
        write_ply(root / "ok.ply", np.zeros((5, 3), np.float32))
        doc: dict = {"format": "graylight-scanset-v1", "views": [{"cloud": "ok.ply"}, {"cloud": "ok.ply", "name": "b"}]}
        if field == "rig":
            doc["rig"] = value
        else:
            doc["views"][0] = {field: value, "name": "a"}
        (root / "scanset.json").write_text(json.dumps(doc))
        load_scanset(root)

    return attempt


def _preview(root: Path, value: str) -> None:
    PreviewOptions.from_mapping({"path": value})


def _store(root: Path, value: str) -> None:
    arts = ArtifactStore(str(root))
    try:
        arts.ref_fingerprint(value)
    except FileNotFoundError:  # as the intake answers it: a leading "/" names the store's root, not the host's
        raise ArtifactError(f"{value}: no such file or folder in storage") from None


#: contract -> (attempt, file suffix, whether the path names a folder, the field its error names)
CONTRACTS = {
    "capture.white": (_capture_image, ".png", False, 'field "white"'),
    "capture.rig": (_capture_rig, ".json", False, ""),
    "scanset.cloud": (_scanset("cloud"), ".ply", False, "views[0]"),
    "scanset.capture": (_scanset("capture"), "", True, "views[0]"),
    "scanset.rig": (_scanset("rig"), ".json", False, "rig"),
    "preview.path": (_preview, ".json", False, "params.preview.path"),
    "capture_ref": (_store, ".zip", False, ""),
}


def _place(kind: str, root: Path, outside: Path, names: list[str], suffix: str, folder: bool, exists: bool) -> str:
    """Lay out the hostile path of ``kind`` (its target there when ``exists``); the value a client writes."""
    rel = "/".join(names) + suffix
    target = outside / rel
    if exists:
        target.parent.mkdir(parents=True, exist_ok=True)
        if folder or kind == "link_dir":
            target.mkdir(exist_ok=True)
            (target / "capture.json").write_text("{}")
        else:
            target.write_bytes(b"ply\nformat ascii 1.0\nend_header\n")
    if kind == "absolute":
        return str(target)
    if kind == "dotdot":
        return "../" * (len(root.parts) + 2) + str(target).lstrip("/")
    if kind == "device_absolute":
        return "/dev/zero"
    link = root / f"{names[0]}_link{suffix}"
    if kind in ("link_file", "link_dir"):
        link.symlink_to(target)
    elif kind == "link_device":
        link.symlink_to("/dev/zero")
    elif kind == "link_fifo":
        fifo = outside / "pipe"
        if not fifo.exists():
            os.mkfifo(fifo)
        link.symlink_to(fifo)
    elif kind == "fifo_inside":
        os.mkfifo(link)
    return link.name


def _refusal(contract: str, kind: str, names: list[str], exists: bool) -> str:
    attempt, suffix, folder, field = CONTRACTS[contract]
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "submission"
        outside = Path(tmp) / "elsewhere"
        root.mkdir()
        outside.mkdir()
        value = _place(kind, root, outside, names, suffix, folder, exists)
        try:
            attempt(root, value)
        except (InputError, ArtifactError) as exc:
            msg = str(exc)
        else:
            raise AssertionError(f"{contract}: {kind} path {value!r} was accepted")
        # Named: the field, or (a FIFO inside the folder, found when the file is opened) the file.
        assert "\n" not in msg and (field in msg or value.rsplit("/", 1)[-1] in msg), (contract, kind, msg)
        # Same value, so the texts may be compared as they are; paths of this run made neutral.
        return msg.replace(tmp, "TMP")


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(contract=st.sampled_from(sorted(CONTRACTS)), kind=st.sampled_from(KINDS), names=_names)
def test_every_hostile_path_is_refused_alike(contract: str, kind: str, names: list[str]) -> None:
    with_target = _refusal(contract, kind, names, exists=True)
    if kind in OUTSIDE:
        assert with_target == _refusal(contract, kind, names, exists=False), contract


def test_every_contract_and_kind_once() -> None:
    """Each pair at least once, whatever hypothesis drew."""
    for contract in CONTRACTS:
        for kind in KINDS:
            with_target = _refusal(contract, kind, ["a", "b"], exists=True)
            if kind in OUTSIDE:
                assert with_target == _refusal(contract, kind, ["a", "b"], exists=False), (contract, kind)


def test_the_worker_copy_of_a_reference_refuses_links_out(tmp_path: Path) -> None:
    """A link placed in a referenced folder after intake, or a FIFO there, is refused when the
    worker copies the folder (finding 8: the worker copied files from outside the store)."""
    store = tmp_path / "store"
    (store / "inbox" / "cap").mkdir(parents=True)
    (store / "inbox" / "cap" / "capture.json").write_text("{}")
    outside = tmp_path / "secret.png"
    outside.write_bytes(b"secret")
    arts = ArtifactStore(str(store))
    (store / "inbox" / "cap" / "white.png").symlink_to(outside)
    for n, cause in enumerate(("link", "fifo")):
        if cause == "fifo":
            (store / "inbox" / "cap" / "white.png").unlink()
            os.mkfifo(store / "inbox" / "cap" / "white.png")
        try:
            arts.ref_read("inbox/cap", tmp_path / f"copy{n}", 1 << 20, 10)
        except ArtifactError as exc:
            assert "inbox/cap/white.png" in str(exc) and "secret" not in str(exc), str(exc)
        else:
            raise AssertionError(f"a {cause} in a referenced folder was copied")
        assert not (tmp_path / f"copy{n}" / "white.png").exists()
