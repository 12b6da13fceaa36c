"""The quadtree range codec with local prediction: round trips (lossless to the quantum,
error-bounded checked on every sample, mask exact) on synthetic, simulated (oversampled smooth
too) and real range images and on hostile arrays; bad input, damaged files, older codec names."""

from __future__ import annotations

import io
import re
import struct
from pathlib import Path

import numpy as np
import pytest

from shared.compress import (
    RangeImage,
    encode_range,
    expected_lossless,
    load_range_npz,
    read_range,
    save_range_npz,
    write_range,
)
from shared.compress.range import CODEC, MAX_SAMPLES, OLD_CODECS
from shared.core.errors import InputError
from shared.formats.container import MAGIC, open_container, write_stream
from tests.support.range_checks import (
    bounded_blob,
    check_bounded,
    check_damage_refused,
    check_lossless,
    chunk_spans,
    lossless_blob,
    rebuilt,
)


def piecewise(h: int = 300, w: int = 420, sigma: float = 0.2, seed: int = 0) -> np.ndarray:
    """A piecewise smooth range image: a tilted plane, a sphere cap standing 40 mm proud
    (a depth jump at its rim), a hole, ragged NaN borders and Gaussian noise ``sigma``."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    z = 900.0 + 0.08 * xx - 0.05 * yy
    cap = (xx - 0.6 * w) ** 2 + (yy - 0.5 * h) ** 2 < (0.25 * h) ** 2
    z[cap] = 860.0 - 0.002 * ((xx[cap] - 0.6 * w) ** 2 + (yy[cap] - 0.5 * h) ** 2)
    z += rng.normal(0.0, sigma, z.shape)
    z[(xx - 0.2 * w) ** 2 + (yy - 0.3 * h) ** 2 < 400] = np.nan
    z[:, : 5 + rng.integers(0, 9, h)[:, None].clip(0, 8).max()] = np.nan
    z[rng.random(z.shape) < 0.01] = np.nan  # speckle of failed decodes
    return z.astype(np.float32)


@pytest.mark.parametrize("q", [0.02, 0.1, 1.0])
def test_lossless_synthetic(q: float) -> None:
    bits = check_lossless(piecewise(), q)
    if q <= 0.2:  # where the noise spans quanta, sigma/q of it costs about log2(sigma/q) + 2.05 bits
        floor = np.log2(0.2 / q) + 2.05
        assert bits < floor + 0.75, (bits, floor)  # the 1 % speckle in the mask costs about 0.4


@pytest.mark.parametrize("e", [0.05, 0.1, 0.5, 1.0, 5.0])
def test_bounded_synthetic(e: float) -> None:
    check_bounded(piecewise(seed=2), e)


def test_coarser_bounds_cost_fewer_bits() -> None:
    z = piecewise(seed=3)
    bits = [check_bounded(z, e) for e in (0.1, 0.5, 1.0)]
    assert bits[0] > bits[1] > bits[2]


def test_discontinuity_blocks_split_and_edges_stay_sharp() -> None:
    # A 50 mm step through the middle of 64x64 blocks: no smearing, every sample within the bound,
    # and the step costs little more than a flat image (the blocks at the edge split).
    h, w = 256, 256
    rng = np.random.default_rng(5)
    flat = (1000.0 + rng.normal(0, 0.2, (h, w))).astype(np.float32)
    step = flat.copy()
    step[:, 101:] -= 50.0
    b_flat, b_step = check_bounded(flat, 0.1), check_bounded(step, 0.1)
    assert b_step < b_flat * 1.1


def test_constant_image_and_all_holes() -> None:
    z = np.full((70, 130), 1234.5, np.float32)
    assert check_lossless(z, 0.02) * z.size / 8 < 600  # bytes: the header and a few symbols
    holes = np.full((65, 70), np.nan, np.float32)
    out = read_range(encode_range(RangeImage(holes), quantum=0.02)).z
    assert out.shape == holes.shape and np.isnan(out).all()


@pytest.mark.parametrize("shape", [(1, 1), (1, 300), (300, 1), (257, 65), (513, 7)])
def test_odd_shapes_and_band_edges(shape: tuple[int, int]) -> None:
    rng = np.random.default_rng(7)
    z = (500 + rng.normal(0, 1.0, shape)).astype(np.float32)
    z[rng.random(shape) < 0.2] = np.nan
    check_lossless(z, 0.05)
    check_bounded(z, 0.3)


def test_simulated_scan_range(sim_range: Path, tmp_path: Path) -> None:
    img = load_range_npz(sim_range)
    assert np.isnan(img.z).any() and (~np.isnan(img.z)).sum() > 10000
    for q in (0.02, 0.5):
        check_lossless(img.z, q)
    for e in (0.1, 0.5, 1.0):
        check_bounded(img.z, e)
    # Through a file, the camera model and units ride along.
    path = tmp_path / "view.glr"
    write_range(path, img, quantum=0.02)
    back = read_range(path)
    np.testing.assert_array_equal(back.K, img.K)
    np.testing.assert_array_equal(back.dist, img.dist)
    assert back.units == img.units


@pytest.mark.slow
def test_real_captures(real_range_files: dict[str, Path]) -> None:
    assert len(real_range_files) == 5
    for name, path in real_range_files.items():
        img = load_range_npz(path)
        assert (~np.isnan(img.z)).mean() > 0.3, name
        check_damage_refused(lossless_blob(img.z, 0.02))
        check_damage_refused(bounded_blob(img.z, 0.1), seed=1)
        check_bounded(img.z, 1.0)


def oversampled(h: int = 200, w: int = 260, seed: int = 0) -> np.ndarray:
    """Smooth sub-pixel-like depth: a curved surface with fine ridges, noise correlated along
    columns (a projector stripe spans several camera pixels) of about 0.05 mm, a shadow hole."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    z = 950.0 + 0.05 * xx + 0.0004 * (yy - h / 2) ** 2 + 1.5 * np.sin(xx / 9.0) * np.cos(yy / 13.0)
    col = np.repeat(rng.normal(0, 0.05, (h, w // 3 + 1)), 3, axis=1)[:, :w]
    z += np.cumsum(col, axis=0) / np.sqrt(np.arange(1, h + 1))[:, None] + rng.normal(0, 0.01, (h, w))
    z[(xx - 0.7 * w) ** 2 + (yy - 0.3 * h) ** 2 < 150] = np.nan
    return z.astype(np.float32)


def test_oversampled_smooth_depth_round_trips_and_local_prediction_pays(monkeypatch: pytest.MonkeyPatch) -> None:
    import shared.compress.range as rg

    z = oversampled()
    bits = {0.02: check_lossless(z, 0.02), 0.1: check_bounded(z, 0.1)}
    # The same image with every leaf on its surface model alone (the encoder's ablation switch;
    # such streams are only measured, not decoded): local prediction must code it smaller.
    monkeypatch.setitem(rg.EFFORTS, 1, 0)
    model_only = len(encode_range(RangeImage(z), quantum=0.02)) * 8 / np.count_nonzero(~np.isnan(z))
    assert bits[0.02] < 0.9 * model_only, (bits, model_only)


def test_simulated_oversampled_scan(sim_capture_factory, tmp_path: Path) -> None:
    # The virtual rig's camera at twice the projector's resolution: sub-pixel depth, smooth and correlated.
    from shared.scan.pipeline import scan

    cap = sim_capture_factory("spheres", size=(256, 192), projector=(128, 96), seed=3)
    scan(cap, tmp_path / "scan")
    z = load_range_npz(tmp_path / "scan" / "range.npz").z
    assert (~np.isnan(z)).sum() > 5000
    check_lossless(z, 0.02)
    for e in (0.05, 0.1, 1.0):
        check_bounded(z, e)


def _hostile() -> list[tuple[str, np.ndarray]]:
    rng = np.random.default_rng(11)
    big = np.float32(3.0e9)
    out = [
        ("random huge values", (rng.standard_normal((70, 90)) * 1e9).astype(np.float32)),
        ("huge and tiny mixed", np.where(rng.random((40, 50)) < 0.5, big, -big).astype(np.float32)),
        ("constant", np.full((66, 70), -12.5, np.float32)),
        ("single valid pixel", np.full((65, 67), np.nan, np.float32)),
        ("1xN", rng.normal(100, 5, (1, 517)).astype(np.float32)),
        ("Nx1", rng.normal(100, 5, (517, 1)).astype(np.float32)),
        ("checkerboard of holes", np.where((np.indices((64, 64)).sum(0) % 2) == 0, 500.0, np.nan).astype(np.float32)),
        ("NaN columns and rows", rng.normal(700, 30, (130, 140)).astype(np.float32)),
        ("alternating depth jumps", np.where(np.indices((80, 80))[1] % 3 == 0, 2000.0, 10.0).astype(np.float32)),
    ]
    out[3][1][33, 40] = 812.25
    out[7][1][:, ::7] = np.nan
    out[7][1][::5, :] = np.nan
    speck = rng.normal(300, 1, (90, 120)).astype(np.float32)
    speck[rng.random(speck.shape) < 0.6] = np.nan
    out.append(("60 % random holes", speck))
    return out


@pytest.mark.parametrize("name, z", _hostile(), ids=[n for n, _ in _hostile()])
def test_hostile_arrays_round_trip(name: str, z: np.ndarray) -> None:
    zmax = float(np.nanmax(np.abs(z))) if (~np.isnan(z)).any() else 1.0
    q = max(0.02, float(np.spacing(np.float32(zmax))) * 4)
    check_lossless(z, q)
    check_bounded(z, max(0.1, 4 * q))


def test_old_codec_name_is_refused_by_name(good_file: bytes) -> None:
    assert CODEC not in OLD_CODECS
    header, chunks = open_container(good_file, kind="range")
    chunks = list(chunks)  # read once, written once per old name
    for old in OLD_CODECS:
        buf = io.BytesIO()
        write_stream(buf, "range", {**header.meta, "codec": old}, chunks)
        with pytest.raises(InputError, match=rf"^<bytes>: range codec '{old}' is not supported \(this build reads '{CODEC}'"):
            read_range(buf.getvalue())


def test_white_noise_bands_code_one_tree_margin(monkeypatch: pytest.MonkeyPatch) -> None:
    """A lossless band whose leaves keep their surface model at the first tree margin (noise
    about a smooth surface) is not coded at the coarser margins: the same stream as with every
    margin coded, one tree a band. Detailed, low-noise depth still tries them all."""
    from shared.compress import _band

    coded = []
    events = _band._encode_events

    def counted(*args, **kw):
        coded.append(args[4])  # the margin
        return events(*args, **kw)

    monkeypatch.setattr(_band, "_encode_events", counted)
    noisy = piecewise(512, 384, sigma=0.2, seed=4)
    blob = encode_range(RangeImage(noisy), quantum=0.02)
    assert coded == [_band.SPLIT_LOSSLESS[0]] * 2  # two bands, the first margin alone
    coded.clear()
    default = _band.MARGIN_MODEL_MAX
    monkeypatch.setattr(_band, "MARGIN_MODEL_MAX", 1.01)  # never skipped
    assert encode_range(RangeImage(noisy), quantum=0.02) == blob
    assert sorted(coded) == sorted(_band.SPLIT_LOSSLESS * 2)
    monkeypatch.setattr(_band, "MARGIN_MODEL_MAX", default)
    coded.clear()
    yy, xx = np.mgrid[0:256, 0:384].astype(np.float64)
    detailed = 900.0 + 0.5 * np.sin(xx / 3.0) * np.cos(yy / 5.0) + np.random.default_rng(4).normal(0, 0.005, xx.shape)
    encode_range(RangeImage(detailed.astype(np.float32)), quantum=0.02)
    assert sorted(coded) == sorted(_band.SPLIT_LOSSLESS)


def test_white_noise_bands_skip_the_bias_trial(monkeypatch: pytest.MonkeyPatch) -> None:
    """Within a bound, a band whose leaves keep their surface model (noise about a smooth
    surface) is not coded with bias cancellation too: the same stream as with the trial made.
    Detailed, low-noise depth still tries it."""
    from shared.compress import _band
    from shared.compress import _lpred as lp

    biased = []
    residuals = lp.encode_residuals

    def counted(*args, **kw):
        biased.append(int(args[7]))  # the bias flag
        return residuals(*args, **kw)

    monkeypatch.setattr(lp, "encode_residuals", counted)
    noisy = piecewise(512, 384, sigma=0.2, seed=5)
    blob = encode_range(RangeImage(noisy), max_error=0.1)
    assert biased and 1 not in biased
    default = _band.BIAS_MODEL_MAX
    monkeypatch.setattr(_band, "BIAS_MODEL_MAX", 1.01)  # always tried
    biased.clear()
    assert encode_range(RangeImage(noisy), max_error=0.1) == blob
    assert 1 in biased
    monkeypatch.setattr(_band, "BIAS_MODEL_MAX", default)
    biased.clear()
    yy, xx = np.mgrid[0:256, 0:384].astype(np.float64)
    detailed = 900.0 + 0.5 * np.sin(xx / 3.0) * np.cos(yy / 5.0) + np.random.default_rng(5).normal(0, 0.005, xx.shape)
    encode_range(RangeImage(detailed.astype(np.float32)), max_error=0.1)
    assert 1 in biased


def test_a_header_claiming_a_huge_image_is_refused_before_allocating() -> None:
    """A decompression bomb: a constant band codes in a few bytes, so a small file could claim
    (and make a worker fill) tens of gigabytes; such a header is refused by name, before the
    image is allocated (a bare MemoryError before), and the encoder refuses such images alike."""
    blob = encode_range(RangeImage(np.full((64, 64), 500.0, np.float32)), quantum=0.02)
    header, chunks = open_container(blob, kind="range")
    chunk = list(chunks)[0]
    for w, h in ((1 << 31, 64), (1 << 40, 64), (200_000, 2_000)):
        nchunks = -(-h // header.meta["band_rows"])
        buf = io.BytesIO()
        write_stream(buf, "range", {**header.meta, "width": w, "height": h, "chunks": nchunks}, [chunk] * nchunks)
        with pytest.raises(InputError, match=rf"^<bytes>: corrupt or hostile range header: it claims a {w} x {h} image"):
            read_range(buf.getvalue())
    # one sample more than the codec's limit (a broadcast view: nothing is allocated)
    side = 1 << 14
    big = np.broadcast_to(np.float32(500.0), (side, MAX_SAMPLES // side + 1))
    with pytest.raises(InputError, match=r"^z: a 16385 x 16384 range image holds 268 M samples, more than the codec's 268 M"):
        encode_range(RangeImage(big), quantum=0.02)


def test_a_header_or_npz_with_a_malformed_camera_or_size_is_refused_by_name(tmp_path: Path) -> None:
    """What a hostile or careless writer puts in a header's fields: sizes that are floats (an
    infinite one overflowed int() with a bare OverflowError), strings or bools, an unknown mode,
    an infinite scale, a camera matrix or distortion that is not one (the decoder handed them on
    to whatever reprojects the image), units that are not a name. Each is refused by name before
    decoding; an npz from elsewhere, and the encoder's input, alike."""
    z = piecewise(64, 48)
    good = RangeImage(z, np.eye(3) * 500.0, np.zeros(5), "mm")
    blob = encode_range(good, quantum=0.02)
    header, chunks = open_container(blob, kind="range")
    payloads = list(chunks)

    def with_meta(**changes: object) -> bytes:
        buf = io.BytesIO()
        write_stream(buf, "range", {**header.meta, **changes}, payloads)
        return buf.getvalue()

    for key, value in (("width", float("inf")), ("width", 64.0), ("width", 1e308), ("height", "48"), ("band_rows", True),
                       ("fine_shift", float("inf")), ("mode", "other"), ("scale", float("inf")), ("scale", "x")):
        with pytest.raises(InputError, match=r"^<bytes>: corrupt or unsupported range header$"):
            read_range(with_meta(**{key: value}))
    for key, value, message in (
            ("K", "abc", "K must be numbers, got 'abc'"),
            ("K", [[1, 2], [3]], "K must be numbers"),
            ("K", [[1, 0, 0], [0, 1, 0]], "K must be a 3 x 3 matrix of finite numbers"),
            ("K", [[1e400, 0, 0], [0, 1, 0], [0, 0, 1]], "K must be a 3 x 3 matrix of finite numbers"),
            ("dist", [0.1, 0.2, 0.3], "dist must be OpenCV's 4, 5, 8, 12, 14 finite distortion coefficients"),
            ("dist", {"k1": 0.1}, "dist must be numbers"),
            ("units", 5, "units must be a short printable name such as mm, got 5"),
            ("units", "mm\nend_header", "units must be a short printable name")):
        with pytest.raises(InputError, match=rf"^<bytes>: corrupt range header: {re.escape(message)}"):
            read_range(with_meta(**{key: value}))
    # no camera at all passes (each band's check is bound to the header: its own file, not
    # this one's header edited)
    cameraless = read_range(encode_range(RangeImage(z), quantum=0.02))
    assert cameraless.K is None and np.isnan(cameraless.z).sum() == np.isnan(z).sum()
    # a valid header rewritten with its CRC: another scale changes the decoded samples (their
    # check), another camera or units would not (the check's binding to the header)
    for key, value in (("scale", 0.04), ("K", None), ("units", "m")):
        with pytest.raises(InputError, match=r"^<bytes>: corrupt chunk 0 \(its decoded samples fail their check\)$"):
            read_range(with_meta(**{key: value}))
    unknown = save_range_npz(tmp_path / "unknown.npz", RangeImage(z))
    assert np.isnan(load_range_npz(unknown).K).all()
    bad = tmp_path / "bad" / "range.npz"
    bad.parent.mkdir()
    np.savez(bad, z=z, K=np.eye(2), dist=np.zeros(5), units=np.array("mm"))
    with pytest.raises(InputError, match=rf"^{bad}: K must be a 3 x 3 matrix"):
        load_range_npz(bad)
    with pytest.raises(InputError, match=r"^range image: dist must be OpenCV's"):
        encode_range(RangeImage(z, np.eye(3), np.zeros(6), "mm"), quantum=0.02)


def test_npz_round_trip_as_a_scan_writes_it(tmp_path: Path) -> None:
    z = piecewise(80, 90)
    img = RangeImage(z, np.eye(3) * 1000.0, np.arange(5.0) / 10, "cm")
    p = save_range_npz(tmp_path / "range.npz", img)
    with np.load(p) as d:
        assert set(d.files) == {"z", "K", "dist", "units"} and d["z"].dtype == np.float32
    back = load_range_npz(p)
    np.testing.assert_array_equal(back.z, z)
    assert back.units == "cm"


# --- bad input ---------------------------------------------------------------------------------


def test_infinite_depth_among_valid_samples() -> None:
    z = piecewise(64, 64)
    z[10, 20] = np.inf
    with pytest.raises(InputError, match="infinite depth.*row 10, column 20"):
        encode_range(RangeImage(z), quantum=0.02)


@pytest.mark.parametrize("kw, match", [
    ({"max_error": 0.0}, "--max-error: must be a positive number"),
    ({"max_error": -1.0}, "--max-error: must be a positive number"),
    ({"max_error": float("nan")}, "--max-error: must be a positive number"),
    ({"quantum": 0.0}, "--quantum: must be a positive number"),
    ({"quantum": 1e-6}, "--quantum: 1e-06 is finer than float32 can hold"),
    ({"max_error": 1e-6}, "--max-error: 1e-06 is finer than float32 can hold"),
    ({}, "exactly one of"),
    ({"quantum": 0.1, "max_error": 0.1}, "exactly one of"),
])  # fmt: skip
def test_bad_parameters(kw: dict, match: str) -> None:
    with pytest.raises(InputError, match=match):
        encode_range(RangeImage(piecewise(64, 64)), **kw)


def test_bad_arrays() -> None:
    with pytest.raises(InputError, match="2-D array"):
        encode_range(RangeImage(np.zeros(5, np.float32)), quantum=0.1)
    with pytest.raises(InputError, match="floating point"):
        encode_range(RangeImage(np.zeros((4, 4), np.int32)), quantum=0.1)


@pytest.fixture(scope="module")
def good_file(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    z = piecewise(520, 100)  # three bands: three chunks
    return encode_range(RangeImage(z), max_error=0.2)


def _write(tmp_path: Path, data: bytes) -> Path:
    p = tmp_path / "x.glr"
    p.write_bytes(data)
    return p


def test_truncated_files_fail_clearly(tmp_path: Path, good_file: bytes) -> None:
    for cut in (3, 12, 30, len(good_file) // 2, len(good_file) - 9, len(good_file) - 1):
        p = _write(tmp_path, good_file[:cut])
        with pytest.raises(InputError, match=rf"^{p}: truncated"):
            read_range(p)


def test_corrupted_bytes_fail_clearly(tmp_path: Path, good_file: bytes) -> None:
    rng = np.random.default_rng(0)
    hdr_end = len(MAGIC) + 12 + struct.unpack_from("<I", good_file, len(MAGIC) + 4)[0]
    for pos in [*rng.integers(len(MAGIC) + 12, hdr_end, 3), *rng.integers(hdr_end, len(good_file) - 8, 12)]:
        bad = bytearray(good_file)
        bad[pos] ^= 0x5A
        p = _write(tmp_path, bytes(bad))
        with pytest.raises(InputError, match=rf"^{p}: (corrupt|truncated)"):
            read_range(p)


def test_wrong_magic_version_kind_and_trailing_bytes(tmp_path: Path, good_file: bytes) -> None:
    with pytest.raises(InputError, match="wrong magic number"):
        read_range(_write(tmp_path, b"PK\x03\x04" + good_file[4:]))
    bad = bytearray(good_file)
    bad[len(MAGIC) : len(MAGIC) + 2] = struct.pack("<H", 7)
    with pytest.raises(InputError, match="container version 7 is not supported"):
        read_range(_write(tmp_path, bytes(bad)))
    with pytest.raises(InputError, match="bytes after the end marker"):
        read_range(_write(tmp_path, good_file + b"\0"))
    with pytest.raises(InputError, match="no such file"):
        read_range(tmp_path / "missing.glr")
    with pytest.raises(InputError, match=rf"^{tmp_path}: a folder, not a compressed file$"):
        read_range(tmp_path)
    with pytest.raises(InputError, match=rf"^{tmp_path}: a folder, not a range.npz file$"):
        load_range_npz(tmp_path)


def test_damaged_payload_with_a_matching_checksum_is_still_caught() -> None:
    # A payload rewritten and re-checksummed (a buggy writer, not line noise) must not decode
    # to a wrong image: the stream's own end check, or the band's check of its decoded samples, catches it.
    import zlib

    z = piecewise(64, 64)
    blob = bytearray(encode_range(RangeImage(z), quantum=0.02))
    hdr_end = len(MAGIC) + 12 + struct.unpack_from("<I", blob, len(MAGIC) + 4)[0]
    length = struct.unpack_from("<I", blob, hdr_end)[0]
    start = hdr_end + 8
    payload = bytearray(blob[start : start + length])
    payload[len(payload) // 2] ^= 0xFF
    blob[start : start + length] = payload
    struct.pack_into("<I", blob, hdr_end + 4, zlib.crc32(bytes(payload)))
    with pytest.raises(InputError, match="corrupt chunk 0"):
        read_range(bytes(blob))


@pytest.mark.parametrize("kw", [{"quantum": 0.02}, {"max_error": 0.1}], ids=["lossless", "bounded"])
def test_a_band_in_another_bands_place_is_refused(kw: dict) -> None:
    """Chunks swapped, or one repeated in another's place, each with its own CRC (a writer's
    mix-up): every chunk is an intact stream of a band of the same size, so only the band's
    check, bound to the band's index, can tell (``quadtree-lp-8`` decoded both to another image)."""
    blob = encode_range(RangeImage(piecewise(768, 300)), **kw)  # three bands of 256 rows
    first, second, third = (blob[a:b] for a, b in chunk_spans(blob))
    assert first != second
    # band 1's chunk in band 0's place; band 0's repeated in band 1's
    for payloads, bad in (([second, first, third], 0), ([first, first, third], 1)):
        with pytest.raises(InputError, match=rf"corrupt chunk {bad} \(its decoded samples fail their check\)"):
            read_range(rebuilt(blob, payloads))
    read_range(rebuilt(blob, [first, second, third]))  # the same frames in their own places


@pytest.mark.parametrize("kw", [{"quantum": 0.02}, {"max_error": 0.1}], ids=["lossless", "bounded"])
def test_damage_the_stream_heals_is_refused_by_the_bands_check(kw: dict) -> None:
    """On flat residual tables (noise of many quanta, as a real capture's) a corrupted rANS state
    often heals: the stream ends where and as it should, yet some samples decode wrong. Search a
    noisy band for such a flip (decoded past the stream's own checks, another image), then check
    the file with it is refused by the band's check of its decoded samples."""
    import zlib

    from shared.compress._band import decode_band

    rng = np.random.default_rng(3)
    z = (600 + rng.normal(0, 2.0, (256, 256))).astype(np.float32)  # about 100 quanta of noise
    z[rng.random(z.shape) < 0.1] = np.nan
    blob = encode_range(RangeImage(z), **kw)
    good = read_range(blob).z
    meta = open_container(blob, kind="range")[0].meta
    lossless, scale = meta["mode"] == "lossless", float(meta["scale"])
    ((start, end),) = chunk_spans(blob)  # one band; its length and CRC-32 in the 8 bytes before
    payload = blob[start:end]
    nt = struct.unpack_from("<I", payload)[0]
    tables = np.frombuffer(payload, np.uint8, nt, 8)
    words0 = np.frombuffer(payload, "<u2", (end - start - 8 - nt) // 2, 8 + nt)
    healed = None
    for k in rng.permutation(words0.size)[:2000]:
        words = words0.copy()
        words[k] ^= np.uint16(1 << int(rng.integers(0, 16)))
        out = np.empty_like(good)
        if decode_band(tables, words, 256, 256, lossless, scale, out) == 0 and not np.array_equal(out, good, equal_nan=True):
            healed = (k, words)
            break
    assert healed is not None, "no flip of 2000 healed: the search no longer finds what this test needs"
    k, words = healed
    bad = bytearray(blob)
    bad[start + 8 + nt : end] = words.astype("<u2").tobytes()
    struct.pack_into("<I", bad, start - 4, zlib.crc32(bytes(bad[start:end])))
    with pytest.raises(InputError, match=r"corrupt chunk 0 \(its decoded samples fail their check\)"):
        read_range(bytes(bad))


def test_weighted_predictor_is_chosen_where_it_pays_and_round_trips() -> None:
    """On a tilted plane with smooth texture (noise blurred over a few samples, 0.3 mm, as a
    camera finer than the projector sees fine relief) and a few holes, the band takes the
    weighted predictor (its stream is smaller than the one coded without it) and decodes
    exactly."""
    from shared.compress import _band as band
    from shared.compress import _lpred as lp
    from shared.compress import _quadtree as qt

    rng = np.random.default_rng(0)
    n = rng.normal(0.0, 1.0, (256, 300))
    k = np.array([1.0, 4.0, 6.0, 4.0, 1.0]) / 16.0
    n = np.apply_along_axis(lambda r: np.convolve(r, k, "same"), 1, n)
    n = np.apply_along_axis(lambda c: np.convolve(c, k, "same"), 0, n)
    z = 900.0 + 0.05 * np.arange(300)[None, :] + 0.3 * n / n.std()
    z[rng.random(z.shape) < 0.002] = np.nan
    z = z.astype(np.float32)
    t, valid = qt.quantise(z, 0.02, True)
    # the least-squares predictor off both ways: it takes these leaves where it runs
    tables, words, _ = band.encode_band(t, valid, True, lp.OPT_ALL & ~lp.OPT_LS, 0.02)
    tables0, words0, _ = band.encode_band(t, valid, True, lp.OPT_ALL & ~lp.OPT_WP & ~lp.OPT_LS, 0.02)
    assert tables.size + 2 * words.size < tables0.size + 2 * words0.size
    out = np.empty(z.shape, np.float32)
    assert band.decode_band(tables, words, z.shape[0], z.shape[1], True, 0.02, out) == 0
    mask = ~np.isnan(z)
    np.testing.assert_array_equal(np.isnan(out), ~mask)
    np.testing.assert_array_equal(out[mask], expected_lossless(z, 0.02)[mask])


@pytest.mark.parametrize("q", [0.02, 0.1])
def test_effort_2_round_trips_and_bad_efforts_are_refused(q: float) -> None:
    """Effort 2 (the weighted predictor tried per lossless band) decodes exactly and is no larger
    than effort 1 on the oversampled image; an effort that is not 1 or 2 is refused by name."""
    z = oversampled()
    mask = ~np.isnan(z)
    sizes = {}
    for effort in (1, 2):
        blob = encode_range(RangeImage(z), quantum=q, effort=effort)
        out = read_range(blob).z
        np.testing.assert_array_equal(np.isnan(out), ~mask)
        np.testing.assert_array_equal(out[mask], expected_lossless(z, q)[mask])
        sizes[effort] = len(blob)
    assert sizes[2] <= sizes[1]
    for bad in (0, 3, True, "2", 1.5):
        with pytest.raises(InputError, match="--effort"):
            encode_range(RangeImage(z), quantum=q, effort=bad)  # type: ignore[arg-type]


def test_masks_coded_against_the_row_above_round_trip() -> None:
    """Silhouettes drifting by 0 to 6 samples a row (edges within reach of the row above's and
    beyond it), islands that appear and vanish, rows all valid or all holes, runs touching both
    ends of the row: the mask decodes exactly, lossless and bounded."""
    rng = np.random.default_rng(5)
    h, w = 300, 257
    yy, xx = np.mgrid[0:h, 0:w]
    left = np.cumsum(rng.integers(-6, 7, h)) % 60
    right = w - 1 - (np.cumsum(rng.integers(-3, 4, h)) % 40)
    keep = (xx >= left[:, None]) & (xx <= right[:, None])
    keep &= ~(((xx - 120) ** 2 + (yy - 150) ** 2 < 900) & (rng.random((h, w)) < 0.3))  # ragged hole
    keep[40:44] = True
    keep[80:83] = False
    keep[100:140:7, 200:203] = False  # islands of holes in single rows
    z = np.where(keep, 800.0 + 0.05 * xx + rng.normal(0, 0.1, (h, w)), np.nan).astype(np.float32)
    check_lossless(z, 0.02)
    check_bounded(z, 0.1)


def test_compact_tables_round_trip_and_refuse_damage() -> None:
    """The log-scale table codes rebuild the frequencies the encoder coded with (every used
    symbol kept, each table summing to the rANS scale); truncated or padded-with-ones tables
    are refused."""
    from shared.compress import _rans, _tables

    rng = np.random.default_rng(3)
    counts = np.zeros((6, _rans.NSYM), np.int64)
    counts[0, :40] = (1e5 * np.exp(-np.arange(40) / 6.0)).astype(np.int64) + 1
    counts[1, 7] = 12  # a single symbol
    counts[3, rng.integers(0, _rans.NSYM, 50)] = rng.integers(1, 10_000, 50)  # sparse, wide
    freq = _rans.normalise(counts)
    codes, coded = _tables.quantise_tables(freq)
    buf = _tables.pack_codes(codes)
    back, used = _tables.unpack_codes(buf, 6)
    assert used == buf.size
    np.testing.assert_array_equal(back, coded)
    np.testing.assert_array_equal(back > 0, counts > 0)
    assert set(back.sum(1)) == {0, _rans.PROB_SCALE}
    # within a step of 2**(1/8) (and the renormalisation) of the exact frequencies
    m = freq > 64
    assert np.abs(np.log2(back[m] / freq[m])).max() < 0.15
    assert _tables.unpack_codes(buf[:-2], 6)[1] == -1
    padded = buf.copy()
    padded[-1] |= 1  # a stray bit after the last code (or a different code)
    res = _tables.unpack_codes(padded, 6)
    assert res[1] == -1 or not np.array_equal(res[0], coded)
