"""Both codecs against damage their container's CRC-32 does not see: a buggy tool, or a hostile
writer, that rewrites the CRCs after changing a chunk's payload or the header. Every damaged
file must be refused with a clear error, or decode to exactly what the intact one decodes to
(a byte the decoder never reads). Found with a fuzzer run in worker processes: on
``quadtree-lp-8`` and ``octree-rans-4`` swapped chunks, a cloud chunk's damaged head or tables,
and a header rewritten with another precision, camera or units decoded to another image or
cloud, with no error."""

from __future__ import annotations

import struct
from collections.abc import Callable

import numpy as np
import pytest

from shared.compress import RangeImage, decode_cloud, encode_cloud, encode_range, read_range
from shared.core.errors import InputError
from shared.formats.container import open_container
from tests.support.range_checks import chunk_spans, rebuilt
from tests.support.range_images import synthetic_range


def _payloads(blob: bytes) -> list[bytes]:
    return [blob[a:b] for a, b in chunk_spans(blob)]


def _damaged(rng: np.random.Generator, payloads: list[bytes], tables_length: bool) -> list[bytes]:
    """One kind of damage to one chunk: a byte, several bytes, a byte near the start (a cloud
    chunk's head, a range band's tables), a payload cut short or extended by whole words,
    another chunk's payload, a run of 0x00 or 0xFF, or (range) the tables' length."""
    out = list(payloads)
    i = int(rng.integers(len(out)))
    p = bytearray(out[i])
    kind = int(rng.integers(7 + tables_length))
    if kind == 0:
        p[int(rng.integers(len(p)))] ^= int(rng.integers(1, 256))
    elif kind == 1:
        for _ in range(int(rng.integers(2, 24))):
            p[int(rng.integers(len(p)))] = int(rng.integers(256))
    elif kind == 2:
        p[int(rng.integers(min(len(p), 80)))] ^= int(rng.integers(1, 256))
    elif kind == 3:
        del p[len(p) - 2 * int(rng.integers(1, max(2, len(p) // 8))) :]
    elif kind == 4:
        p += rng.integers(0, 256, 2 * int(rng.integers(1, 32))).astype(np.uint8).tobytes()
    elif kind == 5:
        p = bytearray(out[(i + 1 + int(rng.integers(len(out) - 1))) % len(out)])
    elif kind == 6:
        a = int(rng.integers(len(p)))
        p[a : a + int(rng.integers(1, 100))] = bytes([0xFF if rng.random() < 0.5 else 0]) * len(p[a : a + 100])
    else:
        struct.pack_into("<I", p, 0, max(0, struct.unpack_from("<I", p)[0] + int(rng.integers(-8, 9))))
    out[i] = bytes(p)
    return out


def _same_or_refused(decode: Callable[[bytes], np.ndarray], good: np.ndarray, data: bytes, what: str) -> bool:
    """True when ``data`` is refused with an InputError naming its source, False when it
    decodes to exactly ``good`` (asserted); any other exception fails the test."""
    try:
        out = decode(data)
    except InputError as exc:
        assert str(exc).startswith("<bytes>: "), (what, str(exc))
        return True
    assert out.tobytes() == good.tobytes(), f"{what}: decoded to something else"
    return False


def _range_cases() -> list[tuple[str, bytes]]:
    rng = np.random.default_rng(5)
    noisy = (600 + rng.normal(0, 2.0, (300, 260))).astype(np.float32)  # a real capture's noise
    noisy[rng.random(noisy.shape) < 0.2] = np.nan
    scene = synthetic_range(512, 384, 0.2, seed=1)
    return [(f"{name} {kw}", encode_range(RangeImage(z), **kw))
            for name, z in (("scene", scene), ("noisy", noisy))
            for kw in ({"quantum": 0.02}, {"quantum": 0.02, "effort": 2}, {"max_error": 0.1})]  # fmt: skip


def _cloud_cases(monkeypatch: pytest.MonkeyPatch) -> list[tuple[str, bytes]]:
    import shared.compress.cloud as cloud

    monkeypatch.setattr(cloud, "CHUNK_POINTS", 3000)  # three chunks of 3000 and one of 1000
    rng = np.random.default_rng(6)
    n = 10_000
    rec = np.zeros(n, [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for axis in "xyz":
        rec[axis] = rng.normal(0, 50, n)
    rec["red"] = rng.integers(0, 256, n)
    return [(f"cloud {g}", encode_cloud(rec, g)) for g in (0.1, 0.5)]


def _z(blob: bytes) -> np.ndarray:
    return read_range(blob).z


@pytest.mark.parametrize("codec", ["range", "cloud"])
def test_chunks_damaged_and_rechecksummed(codec: str, monkeypatch: pytest.MonkeyPatch) -> None:
    cases = _range_cases() if codec == "range" else _cloud_cases(monkeypatch)
    decode = _z if codec == "range" else decode_cloud
    rng = np.random.default_rng(7)
    refused = total = 0
    for name, blob in cases:
        good = decode(blob)
        payloads = _payloads(blob)
        for k in range(50):
            damaged = _damaged(rng, payloads, tables_length=codec == "range")
            if damaged == payloads:
                continue
            total += 1
            refused += _same_or_refused(decode, good, rebuilt(blob, damaged), f"{name}, damage {k}")
    # most damage is refused; what decodes decodes to the intact image (checked above)
    assert refused >= 0.8 * total, (refused, total)


@pytest.mark.parametrize("codec", ["range", "cloud"])
def test_header_fields_rewritten_with_their_crc(codec: str, monkeypatch: pytest.MonkeyPatch) -> None:
    cases = _range_cases()[:3] if codec == "range" else _cloud_cases(monkeypatch)[:1]
    decode = _z if codec == "range" else decode_cloud
    for name, blob in cases:
        good = decode(blob)
        payloads = _payloads(blob)
        meta = open_container(blob)[0].meta
        for key, value in meta.items():
            others = [0, -1, 1, 255, 256, 2**40, 0.5, 1e300, "x", None, True, []]
            if isinstance(value, int | float) and not isinstance(value, bool):
                others += [value * 2, value / 2, value + 1]
            for other in others:
                if other == value and type(other) is type(value):
                    continue
                changed = rebuilt(blob, payloads, {**meta, key: other})
                assert _same_or_refused(decode, good, changed, f"{name}: {key}={other!r}"), \
                    f"{name}: {key}={other!r} decoded, its header changed"  # fmt: skip
