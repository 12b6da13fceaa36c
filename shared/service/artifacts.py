"""The artifact store: stage outputs and captures, content-addressed, over fsspec.

In: a storage URL — a local folder (the default, under ``GRAYLIGHT_DATA_DIR``) or
``s3://bucket/prefix`` (s3fs; ``GRAYLIGHT_S3_ENDPOINT`` for MinIO or moto). Out: objects
named by a key (the SHA-256 hex of a stage's inputs and parameters, or of a capture's
bytes), each a set of files plus ``MANIFEST.json`` listing every file's size and SHA-256.

Layout::

    ROOT/objects/ab/abcdef.../MANIFEST.json         {"key", "prefix", "files": {name: {size, sha256}}}
    ROOT/objects/ab/abcdef.../<writer-id>/<files>   the data the manifest points at
    ROOT/uploads/<upload-id>/<chunk-index>           chunks of a resumable upload

Writes are atomic: every writer puts its files under its own ``<writer-id>`` and the
manifest is written last, in one step (a rename locally, a single PUT on S3). An object
exists exactly when its manifest does, so a reader never sees half an output, and a
duplicate writer (a re-delivered or re-queued task) either finds the manifest and does
nothing or loses the race harmlessly.

Objects never change; one is only ever deleted whole (:meth:`ArtifactStore.delete`). A stage
file that a later stage may make redundant (the raw range image) is therefore stored as an
object of its own under :func:`detached_key`, beside the stage's object.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import shutil
import tempfile
import threading
import time
import uuid
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import fsspec

from shared.core.errors import GraylightError, InputError
from shared.core.paths import confine, open_regular
from shared.service.config import get_settings

log = logging.getLogger(__name__)

MANIFEST = "MANIFEST.json"
_CHUNK = 1 << 20


class ArtifactError(GraylightError):
    """An object is missing or its bytes do not match its manifest."""


@dataclass(frozen=True)
class FileEntry:
    """One file of an object: path inside it (POSIX), size in bytes, SHA-256 hex."""

    name: str
    size: int
    sha256: str


@dataclass(frozen=True)
class Manifest:
    key: str
    prefix: str
    files: dict[str, FileEntry]
    created_at: float

    def to_json(self) -> dict[str, Any]:
        return {
            "key": self.key,
            "prefix": self.prefix,
            "created_at": self.created_at,
            "files": {n: {"size": e.size, "sha256": e.sha256} for n, e in sorted(self.files.items())},
        }

    @classmethod
    def from_json(cls, doc: Mapping[str, Any]) -> Manifest:
        files = {n: FileEntry(n, int(v["size"]), str(v["sha256"])) for n, v in doc["files"].items()}
        return cls(str(doc["key"]), str(doc["prefix"]), files, float(doc.get("created_at", 0.0)))


def sha256_file(path: Path) -> str:
    """SHA-256 hex of a local file, read in 1 MiB chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(_CHUNK), b""):
            h.update(block)
    return h.hexdigest()


def detached_key(key: str, name: str) -> str:
    """The key of the object that holds file ``name`` detached from object ``key`` (SHA-256
    hex of both): found from the stage's key alone, and deletable without touching it."""
    return hashlib.sha256(f"{_check_key(key)}/detached/{_check_name(name)}".encode()).hexdigest()


def _check_key(key: str) -> str:
    if not key or any(c not in "0123456789abcdef" for c in key) or len(key) < 16:
        raise ArtifactError(f"artifact key {key!r} is not a hex digest")
    return key


def _check_name(name: str) -> str:
    parts = name.split("/")
    if not name or name.startswith("/") or any(p in ("", ".", "..") for p in parts) or "\\" in name:
        raise ArtifactError(f"artifact file name {name!r} is not a relative path inside the object")
    return name


class ArtifactStore:
    """Content-addressed objects on a local folder or an S3-compatible bucket."""

    def __init__(self, url: str, s3_endpoint: str | None = None) -> None:
        self.url = url
        self.s3_endpoint = s3_endpoint
        self.is_local = "://" not in url or url.startswith("file://")
        if self.is_local:
            self.root = str(Path(url.removeprefix("file://")).absolute())
        else:
            self.root = url.rstrip("/")
        self._fs: Any = None
        self._fs_pid = -1
        self._lock = threading.Lock()

    # ---- filesystem ------------------------------------------------------------------
    @property
    def fs(self) -> Any:
        # Worker children are forked: an s3fs instance (with its event-loop thread) must
        # not cross a fork, so each process builds its own.
        with self._lock:
            if self._fs is None or self._fs_pid != os.getpid():
                if self.is_local:
                    self._fs = fsspec.filesystem("file", auto_mkdir=True)
                else:
                    protocol = self.root.split("://", 1)[0]
                    kwargs: dict[str, Any] = {"skip_instance_cache": True, "use_listings_cache": False}
                    if protocol == "s3" and self.s3_endpoint:
                        kwargs["client_kwargs"] = {"endpoint_url": self.s3_endpoint}
                    self._fs = fsspec.filesystem(protocol, **kwargs)
                self._fs_pid = os.getpid()
            return self._fs

    def _path(self, *parts: str) -> str:
        return "/".join([self.root, *parts])

    def _obj(self, key: str) -> str:
        key = _check_key(key)
        return self._path("objects", key[:2], key)

    # ---- reading ---------------------------------------------------------------------
    def manifest(self, key: str) -> Manifest | None:
        """The object's manifest, or None when the object does not (yet) exist."""
        path = f"{self._obj(key)}/{MANIFEST}"
        # One whole-object read: s3fs's buffered files pin the ETag for range reads, and a
        # concurrent duplicate writer may replace the manifest in between.
        try:
            data = self.fs.cat_file(path)
        except FileNotFoundError:
            return None
        return Manifest.from_json(json.loads(data.decode()))

    def exists(self, key: str) -> bool:
        return self.manifest(key) is not None

    def _require(self, key: str) -> Manifest:
        m = self.manifest(key)
        if m is None:
            raise ArtifactError(f"artifact {key} does not exist")
        return m

    def _file(self, m: Manifest, name: str) -> str:
        return f"{self._obj(m.key)}/{m.prefix}/{_check_name(name)}"

    def open(self, key: str, name: str) -> IO[bytes]:
        """Open one file of an object for reading (binary)."""
        m = self._require(key)
        if name not in m.files:
            raise ArtifactError(f"artifact {key} has no file {name!r}")
        return self.fs.open(self._file(m, name), "rb")

    def local_file(self, key: str, name: str) -> Path | None:
        """The file's path when the store is a local folder (lets the API send it directly)."""
        if not self.is_local:
            return None
        m = self._require(key)
        if name not in m.files:
            raise ArtifactError(f"artifact {key} has no file {name!r}")
        return Path(self._file(m, name))

    def iter_bytes(self, key: str, name: str, chunk: int = _CHUNK) -> Iterator[bytes]:
        with self.open(key, name) as f:
            while True:
                block = f.read(chunk)
                if not block:
                    return
                yield block

    def iter_range(self, key: str, name: str, start: int, length: int, chunk: int = _CHUNK) -> Iterator[bytes]:
        """``length`` bytes of one file from byte ``start`` (for HTTP range requests)."""
        with self.open(key, name) as f:
            f.seek(start)
            left = length
            while left > 0:
                block = f.read(min(chunk, left))
                if not block:
                    return
                left -= len(block)
                yield block

    def verify(self, key: str) -> Manifest:
        """Re-read every file of an object and check size and SHA-256; raises ArtifactError."""
        m = self._require(key)
        for name, entry in m.files.items():
            h = hashlib.sha256()
            size = 0
            for block in self.iter_bytes(key, name):
                h.update(block)
                size += len(block)
            if size != entry.size or h.hexdigest() != entry.sha256:
                raise ArtifactError(f"artifact {key} file {name}: checksum mismatch")
        return m

    def fetch(self, key: str, cache_dir: Path) -> Path:
        """A local folder holding the object's files. A local store hands back its own folder
        (sizes checked); a remote one is downloaded once into ``cache_dir/key`` with every
        checksum verified, through a temporary folder renamed into place."""
        m = self._require(key)
        if self.is_local:
            base = Path(self._obj(key)) / m.prefix
            for name, entry in m.files.items():
                p = base / name
                if not p.is_file() or p.stat().st_size != entry.size:
                    raise ArtifactError(f"artifact {key} file {name}: missing or truncated")
            return base
        dest = Path(cache_dir) / "objects" / key / m.prefix
        if (dest / ".complete").is_file():
            return dest
        cache_dir = Path(cache_dir)
        cache_dir.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{key[:12]}.", dir=cache_dir))
        try:
            for name, entry in m.files.items():
                target = tmp / name
                target.parent.mkdir(parents=True, exist_ok=True)
                h = hashlib.sha256()
                with self.fs.open(self._file(m, name), "rb") as src, open(target, "wb") as dst:
                    for block in iter(lambda src=src: src.read(_CHUNK), b""):
                        h.update(block)
                        dst.write(block)
                if h.hexdigest() != entry.sha256:
                    raise ArtifactError(f"artifact {key} file {name}: checksum mismatch after download")
            (tmp / ".complete").write_text("")
            dest.parent.mkdir(parents=True, exist_ok=True)
            try:
                os.rename(tmp, dest)
            except OSError:
                # Another process of this machine fetched it first.
                if not (dest / ".complete").is_file():
                    raise
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        return dest

    # ---- writing ---------------------------------------------------------------------
    def put_files(self, key: str, files: Mapping[str, Path]) -> Manifest:
        """Store local files as object ``key`` (names are paths inside the object). When the
        object already exists, nothing is written and its manifest is returned."""
        existing = self.manifest(key)
        if existing is not None:
            return existing
        prefix = uuid.uuid4().hex
        base = f"{self._obj(key)}/{prefix}"
        entries: dict[str, FileEntry] = {}
        try:
            for name, src in sorted(files.items()):
                name = _check_name(name)
                src = Path(src)
                entries[name] = FileEntry(name, src.stat().st_size, sha256_file(src))
                self.fs.put_file(str(src), f"{base}/{name}")
            manifest = Manifest(key, prefix, entries, time.time())
            self._write_manifest(key, manifest)
        except BaseException:
            # A full disk, a failing store: no manifest, so no object; take the files back too,
            # and the object's folder when nothing else is in it.
            self._remove_quietly(base)
            self._remove_empty(self._obj(key))
            raise
        won = self.manifest(key)
        if won is not None and won.prefix != prefix:
            # A concurrent writer's manifest landed first; drop our copy.
            self._remove(base)
            return won
        return manifest

    def put_dir(self, key: str, folder: Path, move: bool = False) -> Manifest:
        """Store every regular file under ``folder`` (recursively) as object ``key``. With
        ``move`` on a local store the folder is renamed into the store instead of copied
        (it must then be on the same filesystem; otherwise it is copied)."""
        folder = Path(folder)
        files = {p.relative_to(folder).as_posix(): p for p in sorted(folder.rglob("*")) if p.is_file() and not p.is_symlink()}
        if not (move and self.is_local):
            return self.put_files(key, files)
        existing = self.manifest(key)
        if existing is not None:
            return existing
        entries = {n: FileEntry(n, p.stat().st_size, sha256_file(p)) for n, p in files.items()}
        for p in sorted(folder.rglob("*"), reverse=True):
            if p.is_symlink() or (not p.is_file() and not p.is_dir()):
                p.unlink()  # only what the manifest lists moves into the store
        prefix = uuid.uuid4().hex
        target = Path(self._obj(key)) / prefix
        target.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.rename(folder, target)
        except OSError:
            return self.put_files(key, files)  # another filesystem: copy instead
        manifest = Manifest(key, prefix, entries, time.time())
        try:
            self._write_manifest(key, manifest)
        except BaseException:
            shutil.rmtree(target, ignore_errors=True)  # no manifest, no object: its files go too
            raise
        won = self.manifest(key)
        if won is not None and won.prefix != prefix:
            shutil.rmtree(target, ignore_errors=True)
            return won
        return manifest

    def _write_manifest(self, key: str, manifest: Manifest) -> None:
        data = json.dumps(manifest.to_json(), indent=1).encode()
        final = f"{self._obj(key)}/{MANIFEST}"
        if self.is_local:
            Path(final).parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=".manifest.", dir=Path(final).parent)
            # No fsync: the data files are not synced either, and a torn object after a
            # power cut is caught by its checksums (verify) and rebuilt under the same key.
            with os.fdopen(fd, "wb") as f:
                f.write(data)
            try:
                # link() refuses to replace: the first complete writer wins.
                os.link(tmp, final)
            except FileExistsError:
                pass
            finally:
                os.unlink(tmp)
        else:
            self.fs.pipe_file(final, data)

    def _remove_quietly(self, path: str) -> None:
        """:meth:`_remove` while another error is on its way up: that error is the one to report."""
        try:
            self._remove(path)
        except Exception as exc:
            log.warning("could not remove the partial object %s: %s", path, exc)

    def _remove_empty(self, path: str) -> None:
        """Remove the local folder ``path`` if it is empty (on S3 a folder is no object)."""
        if self.is_local:
            with contextlib.suppress(OSError):
                os.rmdir(path)

    def _remove(self, path: str) -> None:
        try:
            self.fs.rm(path, recursive=True)
        except FileNotFoundError:
            pass

    def delete(self, key: str) -> None:
        """Remove an object (its manifest first, so it stops existing before its files go)."""
        self._remove(f"{self._obj(key)}/{MANIFEST}")
        self._remove(self._obj(key))

    # ---- resumable uploads -----------------------------------------------------------
    def _upload_dir(self, upload_id: str) -> str:
        if not upload_id or any(c not in "0123456789abcdef-" for c in upload_id):
            raise ArtifactError(f"upload id {upload_id!r} is malformed")
        return self._path("uploads", upload_id)

    def put_chunk(self, upload_id: str, index: int, src: Path) -> None:
        """Store chunk number ``index`` of an upload (the database records the offset); a
        failed write (a full disk) leaves no partial chunk."""
        try:
            self.fs.put_file(str(src), f"{self._upload_dir(upload_id)}/{index:08d}")
        except BaseException:
            self._remove_quietly(f"{self._upload_dir(upload_id)}/{index:08d}")
            raise

    def drop_chunk(self, upload_id: str, index: int) -> None:
        """Remove chunk ``index`` of an upload (one the database did not record)."""
        self._remove(f"{self._upload_dir(upload_id)}/{index:08d}")

    def assemble_upload(self, upload_id: str, chunks: int, dest: Path) -> None:
        """Concatenate an upload's chunks into the local file ``dest``."""
        with open(dest, "wb") as out:
            for i in range(chunks):
                with self.fs.open(f"{self._upload_dir(upload_id)}/{i:08d}", "rb") as f:
                    shutil.copyfileobj(f, out, _CHUNK)

    def drop_upload(self, upload_id: str) -> None:
        self._remove(self._upload_dir(upload_id))

    # ---- references to objects placed in storage by others ---------------------------
    def ref_path(self, ref: str) -> str:
        """The storage path of a reference relative to the store root (``inbox/cap1.zip``). On a
        local store the reference follows the one confinement rule (:func:`shared.core.paths.confine`):
        a symbolic link leading out of the store is refused (:class:`ArtifactError`), with one
        text whatever lies at its target."""
        clean = ref.strip("/")
        _check_name(clean)
        if self.is_local:
            self._confine_local(clean, check=False)
        return self._path(clean)

    def _confine_local(self, rel: str, check: bool = True) -> None:
        """:class:`ArtifactError` unless ``rel`` lies inside the local store, links followed, and
        (``check``) is a regular file or a folder: never a device, FIFO or socket."""
        try:
            confine(self.root, rel, where=rel, folder="store", kind="any", check=check)
        except InputError as exc:
            raise ArtifactError(f"{exc.where}: {exc.problem}") from None

    def ref_info(self, ref: str) -> dict[str, Any]:
        """``fs.info`` of a referenced file or folder; FileNotFoundError when absent."""
        path = self.ref_path(ref)
        if not self.fs.exists(path):
            raise FileNotFoundError(ref)
        if self.is_local:
            self._confine_local(ref.strip("/"))
        return dict(self.fs.info(path))

    def ref_fingerprint(self, ref: str) -> str:
        """A content fingerprint of a referenced file or folder: SHA-256 over each file's
        name, size and ETag or modification time (cheap: no bytes are read)."""
        return self.ref_stat(ref)[0]

    def ref_stat(self, ref: str) -> tuple[str, bool, int]:
        """``(fingerprint, is_folder, bytes)`` of a reference from one listing: the
        :meth:`ref_fingerprint`, whether it is a folder, and its size (a folder's files summed)."""
        path = self.ref_path(ref)
        info = self.ref_info(ref)
        h = hashlib.sha256(ref.encode())
        if info.get("type") == "directory":
            entries = sorted(self.fs.find(path, detail=True).items())
            if self.is_local:  # refused at intake, not by the worker that would copy them
                base = self.fs._strip_protocol(path).rstrip("/")
                for p, _i in entries:
                    self._confine_local(f"{ref.strip('/')}/{self.fs._strip_protocol(p)[len(base) + 1:]}")
        else:
            entries = [(path, info)]
        for p, i in entries:
            tag = i.get("ETag") or i.get("etag") or i.get("mtime") or i.get("LastModified") or ""
            h.update(f"{p}|{i.get('size')}|{tag}".encode())
        size = sum(int(i.get("size") or 0) for _p, i in entries)
        return h.hexdigest(), info.get("type") == "directory", size

    def ref_read(self, ref: str, dest: Path, max_bytes: int, max_files: int) -> Path:
        """Copy a referenced file (or folder, recursively) to local ``dest`` within limits."""
        path = self.ref_path(ref)
        info = self.ref_info(ref)
        if info.get("type") == "directory":
            found = self.fs.find(path, detail=True)
            if len(found) > max_files:
                raise ArtifactError(f"{ref}: {len(found)} files, more than the limit of {max_files}")
            total = sum(int(i.get("size") or 0) for i in found.values())
            if total > max_bytes:
                raise ArtifactError(f"{ref}: {total} bytes, more than the limit of {max_bytes}")
            dest.mkdir(parents=True, exist_ok=True)
            base = self.fs._strip_protocol(path).rstrip("/")
            for p in found:
                rel = self.fs._strip_protocol(p)[len(base) + 1 :]
                _check_name(rel)
                if self.is_local:  # a link inside the folder must not lead out of the store either
                    self._confine_local(f"{ref.strip('/')}/{rel}")
                target = dest / rel
                target.parent.mkdir(parents=True, exist_ok=True)
                self.fs.get_file(p, str(target))
            return dest
        if int(info.get("size") or 0) > max_bytes:
            raise ArtifactError(f"{ref}: {info.get('size')} bytes, more than the limit of {max_bytes}")
        dest.parent.mkdir(parents=True, exist_ok=True)
        if self.is_local:  # regular files only, opened without blocking, read within the limit
            with open_regular(path, ref) as src, open(dest, "wb") as out:
                copied = shutil.copyfileobj(src, out, _CHUNK) or out.tell()
            if copied > max_bytes:
                raise ArtifactError(f"{ref}: more than the limit of {max_bytes} bytes")
            return dest
        self.fs.get_file(path, str(dest))
        return dest


def open_artifacts(url: str | None = None, s3_endpoint: str | None = None) -> ArtifactStore:
    """The configured artifact store (``GRAYLIGHT_STORAGE_URL``, ``GRAYLIGHT_S3_ENDPOINT``)."""
    if url is None:

        cfg = get_settings()
        url, s3_endpoint = cfg.storage_url, cfg.s3_endpoint
    return ArtifactStore(url, s3_endpoint)
