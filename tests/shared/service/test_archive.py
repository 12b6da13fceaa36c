"""Safe archive unpacking: traversal, links, special files, bombs, counts and image headers
are refused before anything is written; a good capture unpacks whole."""

from __future__ import annotations

import io
import tarfile
import zipfile
from pathlib import Path

import numpy as np
import pytest

from shared.core.errors import InputError
from shared.service.archive import ArchiveLimits, extract_archive, inspect_archive, pack_folder
from tests.support.images import png_bytes

LIMITS = ArchiveLimits(max_files=50, max_unpacked_bytes=20 << 20, max_compression_ratio=100,
                       max_image_pixels=4_000_000, max_image_side=4096)  # fmt: skip


def real_png(w: int = 8, h: int = 6) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", np.full((h, w), 128, np.uint8))
    assert ok
    return buf.tobytes()


def make_zip(path: Path, members: dict[str, bytes], compress: bool = False) -> Path:
    with zipfile.ZipFile(
        path, "w", compression=zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    ) as z:
        for name, data in members.items():
            z.writestr(name, data)
    return path


def good_members() -> dict[str, bytes]:
    return {
        "cap/capture.json": b'{"format": "graycode-v1"}',
        "cap/white.png": real_png(),
        "cap/black.png": real_png(),
    }


def assert_nothing_written(dest: Path) -> None:
    assert not dest.exists()
    assert [p.name for p in dest.parent.iterdir()] == []


def test_good_zip_unpacks_into_capture_root(tmp_path: Path) -> None:
    arc = make_zip(tmp_path / "c.zip", good_members())
    report = inspect_archive(arc, LIMITS)
    assert report.root == "cap" and report.kind == "zip"
    assert {m.name: m.image for m in report.members}["cap/white.png"] == (8, 6)
    out = extract_archive(arc, tmp_path / "out" / "x", LIMITS)
    assert out == tmp_path / "out" / "x" / "cap"
    assert (out / "white.png").read_bytes() == real_png()


@pytest.mark.parametrize("name", ["../evil.txt", "/etc/evil", "cap/../../evil", "C:/evil", "cap\\..\\evil"])
def test_traversal_names_refused(tmp_path: Path, name: str) -> None:
    arc = make_zip(tmp_path / "t.zip", {**good_members(), name: b"x"})
    dest = tmp_path / "out" / "x"
    dest.parent.mkdir()
    with pytest.raises(InputError) as e:
        extract_archive(arc, dest, LIMITS)
    assert "t.zip:" in str(e.value) and ("traversal" in str(e.value) or "drive letter" in str(e.value))
    assert_nothing_written(dest)


def _tar(path: Path, build) -> Path:
    with tarfile.open(path, "w:gz") as t:
        for name, data in good_members().items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            t.addfile(info, io.BytesIO(data))
        build(t)
    return path


@pytest.mark.parametrize("kind", [tarfile.SYMTYPE, tarfile.LNKTYPE, tarfile.CHRTYPE, tarfile.FIFOTYPE])
def test_tar_links_and_special_files_refused(tmp_path: Path, kind: bytes) -> None:
    def add(t: tarfile.TarFile) -> None:
        info = tarfile.TarInfo("cap/link.png")
        info.type = kind
        info.linkname = "/etc/passwd"
        t.addfile(info)

    arc = _tar(tmp_path / "l.tar.gz", add)
    dest = tmp_path / "out" / "x"
    dest.parent.mkdir()
    with pytest.raises(InputError, match=r"l\.tar\.gz:cap/link\.png: member is (a link|a device)"):
        extract_archive(arc, dest, LIMITS)
    assert_nothing_written(dest)


def test_zip_symlink_refused(tmp_path: Path) -> None:
    arc = tmp_path / "s.zip"
    with zipfile.ZipFile(arc, "w") as z:
        for n, d in good_members().items():
            z.writestr(n, d)
        info = zipfile.ZipInfo("cap/evil")
        info.external_attr = 0o120777 << 16  # S_IFLNK
        z.writestr(info, "/etc/passwd")
    with pytest.raises(InputError, match="symbolic link"):
        inspect_archive(arc, LIMITS)


def test_zip_bomb_refused_by_ratio(tmp_path: Path) -> None:
    arc = make_zip(tmp_path / "b.zip", {**good_members(), "cap/zeros.bin": b"\0" * (8 << 20)}, compress=True)
    with pytest.raises(InputError, match=r"b\.zip:cap/zeros\.bin: compression ratio \d+:1 exceeds 100:1"):
        inspect_archive(arc, LIMITS)


def test_tar_bomb_refused_by_total(tmp_path: Path) -> None:
    def add(t: tarfile.TarFile) -> None:
        info = tarfile.TarInfo("cap/zeros.bin")
        info.size = 30 << 20
        t.addfile(info, io.BytesIO(b"\0" * info.size))

    arc = _tar(tmp_path / "b.tar.gz", add)
    with pytest.raises(InputError, match=r"b\.tar\.gz: unpacks to more than"):
        inspect_archive(arc, LIMITS)


def test_file_count_limit(tmp_path: Path) -> None:
    arc = make_zip(tmp_path / "n.zip", {**good_members(), **{f"cap/f{i}.txt": b"x" for i in range(60)}})
    with pytest.raises(InputError, match=r"n\.zip: more than 50 members"):
        inspect_archive(arc, LIMITS)


def test_image_header_dimensions_checked_without_decoding(tmp_path: Path) -> None:
    arc = make_zip(tmp_path / "i.zip", {**good_members(), "cap/col_00.png": png_bytes(60000, 40)})
    with pytest.raises(InputError, match=r"i\.zip:cap/col_00\.png: image is 60000x40, a side exceeds"):
        inspect_archive(arc, LIMITS)
    arc = make_zip(tmp_path / "p.zip", {**good_members(), "cap/col_00.png": png_bytes(4000, 4000)})
    with pytest.raises(InputError, match=r"16000000 pixels, more than the limit of 4000000"):
        inspect_archive(arc, LIMITS)
    arc = make_zip(tmp_path / "g.zip", {**good_members(), "cap/col_00.png": b"not an image at all"})
    with pytest.raises(InputError, match=r"g\.zip:cap/col_00\.png: not a readable image header"):
        inspect_archive(arc, LIMITS)


def test_not_an_archive_and_missing_capture_json(tmp_path: Path) -> None:
    junk = tmp_path / "junk.zip"
    junk.write_bytes(b"hello, I am not a zip")
    with pytest.raises(InputError, match=r"junk\.zip: not a zip or tar archive"):
        inspect_archive(junk, LIMITS)
    arc = make_zip(tmp_path / "nc.zip", {"cap/white.png": real_png()})
    with pytest.raises(InputError, match=r"nc\.zip: no capture\.json in the archive"):
        inspect_archive(arc, LIMITS)
    assert inspect_archive(arc, LIMITS, require=None).root == "cap"


def test_pack_folder_round_trip(tmp_path: Path) -> None:
    src = tmp_path / "src"
    (src / "sub").mkdir(parents=True)
    (src / "capture.json").write_text("{}")
    (src / "sub" / "white.png").write_bytes(real_png())
    (src / "link.png").symlink_to(src / "sub" / "white.png")
    arc = pack_folder(src, tmp_path / "p.zip")
    names = sorted(zipfile.ZipFile(arc).namelist())
    assert names == ["capture.json", "sub/white.png"]  # links are not followed into the archive
    out = extract_archive(arc, tmp_path / "o", LIMITS)
    assert (out / "sub" / "white.png").read_bytes() == real_png()
