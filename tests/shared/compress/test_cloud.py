"""The octree cloud codec: every point within half the precision per axis, attributes as
stated (colour and integers exact, normals within NORMAL_MAX_DEG, size and confidence to
their steps), duplicates kept, PLY round trip, bad input and damaged files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from numba import njit

from shared.compress.cloud import (
    CONFIDENCE_STEP,
    MAX_POINTS,
    NORMAL_MAX_DEG,
    SIZE_STEP_OF_PRECISION,
    decode_cloud,
    encode_cloud,
    read_cloud_to_ply,
    write_cloud,
)
from shared.core.errors import InputError
from shared.formats.container import open_container, write_stream
from shared.formats.ply import CLOUD_DTYPE, iter_ply_records, read_header, write_ply_records

MERGED = np.dtype(CLOUD_DTYPE.descr + [("view", "<u2"), ("confidence", "<f4"), ("weird", "<f8")])


def surface_cloud(n_side: int = 300, seed: int = 0, dtype: np.dtype = MERGED) -> np.ndarray:
    """A noisy curved sheet sampled like a range image (0.3 mm pitch), with every attribute."""
    rng = np.random.default_rng(seed)
    u, v = np.meshgrid(np.arange(n_side) * 0.3, np.arange(n_side) * 0.3)
    z = 800 + 0.002 * (u - 45) ** 2 + rng.normal(0, 0.2, u.shape)
    rec = np.zeros(u.size, dtype)
    rec["x"], rec["y"], rec["z"] = u.ravel() - 40, v.ravel() + 12, z.ravel()
    if "red" not in (dtype.names or ()):
        return rec
    rec["red"] = rng.integers(0, 256, u.size)
    rec["green"] = np.clip(rec["red"].astype(int) + rng.integers(-5, 6, u.size), 0, 255)
    rec["blue"] = 200
    n = np.stack([0.004 * (u - 45), np.zeros_like(u), -np.ones_like(u)], -1).reshape(-1, 3) + rng.normal(0, 0.02, (u.size, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    rec["nx"], rec["ny"], rec["nz"] = n.T
    rec["size"] = rec["z"] / 3000.0
    if "view" in (dtype.names or ()):
        rec["view"] = rng.integers(0, 36, u.size)
        rec["confidence"] = rng.random(u.size)
        rec["weird"] = rng.normal(size=u.size)
    return rec


def _match(a: np.ndarray, b: np.ndarray, precision: float) -> tuple[np.ndarray, np.ndarray]:
    """Pair input and decoded points: sort both by voxel (the decoder returns Morton order)."""
    def key(r: np.ndarray) -> np.ndarray:
        q = np.floor(np.stack([r["x"], r["y"], r["z"]], 1).astype(np.float64) / precision).astype(np.int64)
        return np.lexsort(q.T[::-1])
    return a[key(a)], b[key(b)]


@pytest.mark.parametrize("precision", [0.1, 0.5, 2.0])
def test_round_trip_every_point_and_attribute(precision: float) -> None:
    rec = surface_cloud()
    out = decode_cloud(encode_cloud(rec, precision))
    assert out.dtype == rec.dtype and len(out) == len(rec)
    a, b = _match(rec, out, precision)
    for axis in "xyz":
        err = np.abs(a[axis].astype(np.float64) - b[axis])
        assert err.max() <= precision / 2 * (1 + 1e-5) + np.spacing(np.float32(900)), axis
    for f in ("red", "green", "blue", "view", "weird"):
        np.testing.assert_array_equal(a[f], b[f])
    na = np.stack([a["nx"], a["ny"], a["nz"]], 1).astype(np.float64)
    nb = np.stack([b["nx"], b["ny"], b["nz"]], 1).astype(np.float64)
    ang = np.degrees(np.arccos(np.clip((na * nb).sum(1), -1, 1)))
    assert ang.max() <= NORMAL_MAX_DEG
    assert np.abs(a["size"] - b["size"]).max() <= precision * SIZE_STEP_OF_PRECISION / 2 * 1.001
    assert np.abs(a["confidence"] - b["confidence"]).max() <= CONFIDENCE_STEP / 2 * 1.001


def test_duplicates_and_coincident_points_survive() -> None:
    rec = surface_cloud(40, dtype=CLOUD_DTYPE)
    rec = np.concatenate([rec, rec[:500], rec[:7]])
    out = decode_cloud(encode_cloud(rec, 0.5))
    assert len(out) == len(rec)
    a, b = _match(rec, out, 0.5)
    assert np.abs(a["x"] - b["x"]).max() <= 0.25 * 1.0001


def test_coarser_grids_cost_fewer_bits() -> None:
    rec = surface_cloud(dtype=np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4")]))
    sizes = [len(encode_cloud(rec, p)) for p in (0.1, 0.5, 2.0)]
    assert sizes[0] > sizes[1] > sizes[2]


def test_several_chunks_and_ply_files(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import shared.compress.cloud as cloud

    monkeypatch.setattr(cloud, "CHUNK_POINTS", 10_000)  # small chunks: many of them, in parallel
    rec = surface_cloud(150)
    ply = write_ply_records(tmp_path / "in.ply", iter([rec]), len(rec), rec.dtype, ("units mm", "frame camera"))
    size = write_cloud(tmp_path / "c.glo", ply, 0.25)
    assert size == (tmp_path / "c.glo").stat().st_size
    out_ply = read_cloud_to_ply(tmp_path / "c.glo", tmp_path / "out.ply")
    h = read_header(out_ply)
    assert h.count == len(rec) and h.dtype.names == rec.dtype.names and "units mm" in h.comments
    out = np.concatenate(list(iter_ply_records(out_ply)))
    a, b = _match(rec, out, 0.25)
    np.testing.assert_array_equal(a["view"], b["view"])
    assert np.abs(a["z"].astype(np.float64) - b["z"]).max() <= 0.125 * 1.0001


def test_bad_input(tmp_path: Path) -> None:
    rec = surface_cloud(20, dtype=CLOUD_DTYPE)
    for p in (0.0, -1.0, float("inf")):
        with pytest.raises(InputError, match="--precision: must be a positive number"):
            encode_cloud(rec, p)
    with pytest.raises(InputError, match="--precision: 1e-06 is too fine"):
        encode_cloud(rec, 1e-6)
    bad = rec.copy()
    bad["y"][17] = np.nan
    with pytest.raises(InputError, match="point 17 has a non-finite coordinate"):
        encode_cloud(bad, 0.5)


def test_damaged_cloud_files(tmp_path: Path) -> None:
    blob = encode_cloud(surface_cloud(60), 0.5)
    rng = np.random.default_rng(1)
    for pos in rng.integers(40, len(blob) - 8, 10):
        bad = bytearray(blob)
        bad[pos] ^= 0x21
        p = tmp_path / "bad.glo"
        p.write_bytes(bytes(bad))
        with pytest.raises(InputError, match=rf"^{p}: (corrupt|truncated)"):
            decode_cloud(p)
    p = tmp_path / "short.glo"
    p.write_bytes(blob[: len(blob) - 20])
    with pytest.raises(InputError, match="truncated"):
        decode_cloud(p)


def test_chunks_rewritten_with_a_fresh_crc_are_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    """Damage the container's CRC-32 cannot see (a buggy tool rewrote it): a chunk's offset
    changed (``octree-rans-4`` decoded it, every point of the chunk shifted), chunks swapped (each
    an intact stream), the header's precision (every point scaled), and one random byte a copy,
    in the head, the tables or the words: each refused by the chunk's check of what it decodes
    to, or decoded to exactly the intact cloud."""
    import struct

    import shared.compress.cloud as cloud
    from tests.support.range_checks import chunk_spans, rebuilt

    monkeypatch.setattr(cloud, "CHUNK_POINTS", 4000)
    blob = encode_cloud(surface_cloud(100), 0.5)  # 10,000 points: two equal chunks and a short one
    good = decode_cloud(blob)
    spans = chunk_spans(blob)
    assert len(spans) == 3

    payloads = [blob[a:b] for a, b in spans]
    assert decode_cloud(rebuilt(blob, payloads)).tobytes() == good.tobytes()
    shifted = bytearray(payloads[1])
    struct.pack_into("<q", shifted, 24, struct.unpack_from("<q", shifted, 24)[0] + 3)  # the x offset
    with pytest.raises(InputError, match=r"corrupt chunk 1 \(what it decodes to fails its check\)"):
        decode_cloud(rebuilt(blob, [payloads[0], bytes(shifted), payloads[2]]))
    with pytest.raises(InputError, match=r"corrupt chunk 0 \(what it decodes to fails its check\)"):
        decode_cloud(rebuilt(blob, [payloads[1], payloads[0], payloads[2]]))
    # the header rewritten with its CRC: another precision would scale every point
    header, _ = open_container(blob, kind="cloud")
    with pytest.raises(InputError, match=r"corrupt chunk 0 \(what it decodes to fails its check\)"):
        decode_cloud(rebuilt(blob, payloads, {**header.meta, "precision": 1.0}))
    rng = np.random.default_rng(2)
    refused = 0
    for _ in range(60):
        i = int(rng.integers(3))
        bad = bytearray(payloads[i])
        pos = int(rng.integers(len(bad)))
        bad[pos] ^= int(rng.integers(1, 256))
        try:
            out = decode_cloud(rebuilt(blob, [bytes(bad) if j == i else p for j, p in enumerate(payloads)]))
        except InputError as exc:
            assert f"corrupt chunk {i}" in str(exc), exc
            refused += 1
        else:
            assert out.tobytes() == good.tobytes(), f"chunk {i}: byte {pos} damaged decoded to another cloud"
    assert refused >= 50, refused


def test_a_header_claiming_a_huge_cloud_is_refused_before_allocating(tmp_path: Path,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """A decompression bomb: equal points code in almost no bits (4 M points in about a kilobyte,
    130 MB decoded), so a small file can claim, and really decode, gigabytes. A header claiming
    more than the codec's limit is refused by name before anything is allocated or written, the
    encoder refuses such clouds alike, and a PLY that would not fit its disk is refused before
    decoding starts (nothing written)."""
    import io
    import shutil

    import shared.compress.cloud as cloud

    same = np.zeros(1 << 20, CLOUD_DTYPE)
    same["z"], same["nz"] = 500.0, 1.0
    blob = encode_cloud(same, 0.5)
    assert len(blob) < 2000 and len(decode_cloud(blob)) == len(same)  # the bomb's ratio, for real
    header, chunks = open_container(blob, kind="cloud")
    payloads = list(chunks)
    chunk = payloads[0]
    per = 1 << 24
    for points in (MAX_POINTS + 1, 1 << 40):
        n = -(-points // per)
        buf = io.BytesIO()
        write_stream(buf, "cloud", {**header.meta, "points": points, "chunk_points": per, "chunks": n},
                     (chunk for _ in range(n)))
        bomb = tmp_path / "bomb.glo"
        bomb.write_bytes(buf.getvalue())
        message = rf"^{bomb}: corrupt or hostile cloud header: it claims {points / 1e6:.0f} M points, more than the codec's 268 M"
        with pytest.raises(InputError, match=message):
            decode_cloud(bomb)
        with pytest.raises(InputError, match=message):
            read_cloud_to_ply(bomb, tmp_path / "out.ply")
        assert not (tmp_path / "out.ply").exists()
    # a negative count whose chunk count adds up (0 chunks): a bare ValueError from numpy before;
    # counts that are not JSON integers (an infinite one was a bare OverflowError from int())
    for claim in ({"points": -5, "chunks": 0}, {"points": float("inf")}, {"chunk_points": float("inf")},
                  {"points": float(len(same))}, {"points": str(len(same))},
                  {"precision": float("inf")}):  # decoded every coordinate as infinity before
        buf = io.BytesIO()
        write_stream(buf, "cloud", {**header.meta, **claim}, payloads if claim.get("chunks") != 0 else [])
        with pytest.raises(InputError, match=r"^<bytes>: corrupt or unsupported cloud header"):
            decode_cloud(buf.getvalue())
    # one point more than the limit (a broadcast view: nothing is allocated)
    with pytest.raises(InputError, match=r"^cloud: a cloud of 268 M points is more than the codec's 268 M"):
        encode_cloud(np.broadcast_to(same[:1], (MAX_POINTS + 1,)), 0.5)
    # within the limit, but more than the output's disk holds (a full disk, as the check sees it):
    # 1 M points of 31 bytes
    good = tmp_path / "same.glo"
    good.write_bytes(blob)
    free = len(same) * CLOUD_DTYPE.itemsize - 1
    monkeypatch.setattr(cloud.shutil, "disk_usage", lambda p: shutil._ntuple_diskusage(free * 2, free, free))
    with pytest.raises(InputError, match=rf"^{tmp_path / 'sub' / 'out.ply'}: the decoded cloud needs 32.5 MB, and its folder has 32.5 MB free"):
        read_cloud_to_ply(good, tmp_path / "sub" / "out.ply")
    assert not (tmp_path / "sub").exists()


def test_other_codec_versions_fail_clearly(monkeypatch: pytest.MonkeyPatch) -> None:
    import shared.compress.cloud as cloud

    rec = surface_cloud(20, dtype=CLOUD_DTYPE)
    monkeypatch.setattr(cloud, "CODEC", "octree-rans-4")  # what the previous version wrote
    old = encode_cloud(rec, 0.5)
    monkeypatch.undo()
    with pytest.raises(InputError, match=r"cloud codec 'octree-rans-4' is not supported \(this build reads 'octree-rans-5'"):
        decode_cloud(old)


def test_models_adapt_to_a_scan_like_surface() -> None:
    # The neighbour contexts must pay: a range-scan-like sheet at a grid a third of its point
    # spacing costs 6.53 bits a point (octree-rans-3: 6.73; octree-rans-2, without the mixed
    # single-child events of the last levels: 7.3; octree-rans-1's parent and sibling byte
    # contexts: 9.0).
    rec = surface_cloud(300, dtype=np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4")]))
    bits = len(encode_cloud(rec, 0.1)) * 8 / len(rec)
    assert bits < 7.0, bits


def test_secondary_estimation_tables_match_their_definition() -> None:
    # The tables are literal integers (encoder and decoder must agree on every machine); they
    # are what the docstring's formulas give, to the rounding.
    import shared.compress._octree as ot

    p = np.arange(4096)
    logit = np.log((p + 0.5) / (4096 - p - 0.5))
    np.testing.assert_array_equal(ot.SSE_BUCKET, np.clip(((logit + 7) / 14 * ot.SSE_N).astype(np.int64), 0, ot.SSE_N - 1))
    m = np.arange(len(ot.SSE_INIT_M))
    want = 65536 / (1 + np.exp(-(0.0875 * m - 7.21875)))
    assert np.abs(ot.SSE_INIT_M - want).max() <= 1
    assert ot.SSE_INIT.shape == (ot.SSE_N**3,) and ot.SSE_INIT_M.max() == ot.SSE_INIT_M[-1]


def test_model_update_rates_match_their_definition() -> None:
    # The shifts are integers computed without floating point (encoder and decoder agree on
    # every machine); they are log2(n + 2) rounded, at least 1, and a fresh model learns its
    # first events at about their running frequency.
    from shared.compress._rans import MODEL_INIT, MODEL_LIMIT, RATE_SHIFT, state_next, state_p

    n = np.arange(len(RATE_SHIFT))
    np.testing.assert_array_equal(RATE_SHIFT, np.maximum(1, np.floor(np.log2(n + 2) + 0.5)).astype(np.int64))
    assert RATE_SHIFT[MODEL_LIMIT] == 5
    @njit
    def three_ones(s: np.uint32) -> np.uint32:  # state_next is a kernel helper: called from a kernel
        for _ in range(3):
            s = state_next(s, 1)
        return s

    assert state_p(three_ones(np.uint32(MODEL_INIT))) > 0.85 * 4096  # three ones: 1 - 1/2 * 1/2 * 3/4 (the rate of 1/4 rounds 1/3 down)


def test_model_priors_match_their_definition() -> None:
    # The priors are literal integers trained offline (tests/bench/train_cloud_prior.py); their
    # regions must be the models' regions of the kernels (or a prior would land on another
    # context's model), their groups cover every model, and every model starts from its group's
    # probability with a count of zero.
    import shared.compress._octree as ot
    from shared.compress._octree_prior import PRIOR_BOUNDS, PRIOR_P12, PRIOR_SHIFTS

    starts = (ot.C_BIT, ot.C_SINGLE, ot.C_X, ot.C_Y, ot.C_Z, ot.B_X, ot.B_Y, ot.C3_X, ot.C3_Y, ot.B_SINGLE, ot.C3_SINGLE, ot.N_MODELS)
    np.testing.assert_array_equal(PRIOR_BOUNDS, starts)
    assert ot.N_OCC_CTX == ot.B_X and len(PRIOR_SHIFTS) == len(PRIOR_BOUNDS) - 1
    sizes = np.diff(PRIOR_BOUNDS)
    groups = (sizes + (1 << PRIOR_SHIFTS) - 1) >> PRIOR_SHIFTS
    assert groups.sum() == len(PRIOR_P12)
    # half-way between 1/2 and a frequency: within [1/4, 3/4]
    assert PRIOR_P12.min() >= 1024 and PRIOR_P12.max() <= 3072
    first = np.concatenate(([0], np.cumsum(groups)[:-1]))
    want = np.concatenate([PRIOR_P12[g + (np.arange(n) >> s)] for g, n, s in zip(first, sizes, PRIOR_SHIFTS, strict=True)])
    got = ot._prior_states()
    assert got.dtype == np.uint32 and got.shape == (ot.N_MODELS,)
    np.testing.assert_array_equal(got, want.astype(np.uint32) << 4)
