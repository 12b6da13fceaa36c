"""The range codec's round-trip and damage checks, shared by its tests: lossless to the quantum
(every sample, the mask exact), error-bounded (every sample within the bound, the mask exact),
and damaged streams refused or decoded to the very same image (never a wrong one)."""

from __future__ import annotations

import json
import struct
import zlib

import numpy as np
import pytest

from shared.compress import RangeImage, encode_range, expected_lossless, read_range
from shared.core.errors import InputError
from shared.formats.container import MAGIC, TRAILER

_CHUNK = struct.Struct("<II")
_FIXED = struct.Struct("<HBBII")  # the container's version, kind, flags, header length and CRC


def check_lossless(z: np.ndarray, q: float) -> float:
    """Encode ``z`` lossless at quantum ``q``, decode it, check every sample and the mask;
    returns bits per valid sample."""
    return len(lossless_blob(z, q)) * 8 / np.count_nonzero(~np.isnan(z))


def lossless_blob(z: np.ndarray, q: float) -> bytes:
    """:func:`check_lossless`'s stream, checked."""
    blob = encode_range(RangeImage(z), quantum=q)
    out = read_range(blob).z
    mask = ~np.isnan(z)
    np.testing.assert_array_equal(np.isnan(out), ~mask)
    np.testing.assert_array_equal(out[mask], expected_lossless(z, q)[mask])
    assert np.abs(out[mask].astype(np.float64) - z[mask]).max() <= q / 2 + np.spacing(np.float32(np.nanmax(np.abs(z))))
    return blob


def check_bounded(z: np.ndarray, e: float) -> float:
    """Encode ``z`` within ``e``, decode it, check every sample and the mask; returns bits per
    valid sample."""
    return len(bounded_blob(z, e)) * 8 / np.count_nonzero(~np.isnan(z))


def bounded_blob(z: np.ndarray, e: float) -> bytes:
    """:func:`check_bounded`'s stream, checked."""
    blob = encode_range(RangeImage(z), max_error=e)
    out = read_range(blob).z
    mask = ~np.isnan(z)
    np.testing.assert_array_equal(np.isnan(out), ~mask)
    err = np.abs(out[mask].astype(np.float64) - z[mask].astype(np.float64))
    print(f"max error {err.max():.6g} <= {e}")
    assert err.max() <= e
    return blob


def chunk_spans(blob: bytes) -> list[tuple[int, int]]:
    """(start, end) byte offsets of each chunk's payload in a container ``blob``; each payload's
    length and CRC-32 sit in the 8 bytes before its start."""
    pos = len(MAGIC) + 12 + struct.unpack_from("<I", blob, len(MAGIC) + 4)[0]
    spans = []
    while blob[pos : pos + len(TRAILER)] != TRAILER:
        length, _ = _CHUNK.unpack_from(blob, pos)
        spans.append((pos + 8, pos + 8 + length))
        pos += 8 + length
    return spans


def rebuilt(blob: bytes, payloads: list[bytes], meta: dict | None = None) -> bytes:
    """The container ``blob`` with its chunks replaced by ``payloads`` (and its header document
    by ``meta``), every CRC-32 rewritten to match: what a buggy tool that recomputes checksums
    writes."""
    hl = struct.unpack_from("<I", blob, len(MAGIC) + 4)[0]
    head = blob[: len(MAGIC) + _FIXED.size + hl]
    if meta is not None:
        version, kind, flags, _, _ = _FIXED.unpack_from(blob, len(MAGIC))
        doc = json.dumps(meta, separators=(",", ":")).encode()
        head = MAGIC + _FIXED.pack(version, kind, flags, len(doc), zlib.crc32(doc)) + doc
    return head + b"".join(_CHUNK.pack(len(p), zlib.crc32(p)) + p for p in payloads) + TRAILER


def check_damage_refused(blob: bytes, seed: int = 0) -> int:
    """Damage a range stream as a disk, a network or a buggy writer would, and check each
    damaged copy is refused with a clear error, or (a byte the decoder never reads) decodes to
    exactly the image the intact stream gives: cut short at three places; in every chunk, a byte
    flipped (its checksum catches it) and another flipped with the checksum rewritten (only the
    stream's own checks, its end state and the check of the band's decoded samples, can catch
    it). Returns how many damaged copies those refused (at least one a chunk is asserted)."""
    good = read_range(blob).z
    for cut in (len(blob) // 3, len(blob) // 2, len(blob) - 1):
        with pytest.raises(InputError, match="truncated"):
            read_range(blob[:cut])
    rng = np.random.default_rng(seed)
    refused = 0
    for i, (a, b) in enumerate(chunk_spans(blob)):
        bad = bytearray(blob)
        bad[int(rng.integers(a, b))] ^= 0x5A
        with pytest.raises(InputError, match=rf"corrupt chunk {i} \(checksum mismatch\)"):
            read_range(bytes(bad))
        caught = 0
        for pos in rng.integers(a, b, 3):
            bad = bytearray(blob)
            bad[int(pos)] ^= 0xFF
            struct.pack_into("<I", bad, a - 4, zlib.crc32(bytes(bad[a:b])))
            try:
                out = read_range(bytes(bad)).z
            except InputError as exc:
                assert f"corrupt chunk {i}" in str(exc), exc
                caught += 1
            else:
                np.testing.assert_array_equal(out, good, err_msg=f"chunk {i}: a damaged byte at {pos} decoded to another image")
        assert caught >= 1, f"chunk {i}: none of 3 damaged bytes was refused"
        refused += caught
    return refused
