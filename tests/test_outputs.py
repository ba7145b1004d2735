"""The per-position outputs, written the fast way: the results file's chunks compressed by
c-blosc directly, the EXR uncompressed, the PNG tone-mapped in one pass. Everything must
read back exactly, through the project's readers and through the plain libraries."""

from __future__ import annotations

import io
import subprocess
import sys

import blosc
import cv2
import h5py
import hdf5plugin
import numpy as np
import OpenEXR
import pytest
from PIL import Image

from processing.hdr.brackets import merge_raw
from processing.hdr.model import MergeResult, NoiseModel
from processing.images import encode_png, read_exr, tonemap, write_exr, write_png
from processing.results import (
    HDRInfo,
    Results,
    ResultsError,
    ResultsWriter,
    encode_hdr,
    position_file_for,
    stored_variance,
)

NAMES = ("radiance", "variance", "count", "saturated")


def _merge(seed: int = 0, shape=(64, 96)) -> MergeResult:
    """A merge like a mirror ball's: dark noise quantised as the merge leaves it, a few
    bright blobs, some pixels without a sample (NaN), a saturated core."""
    rng = np.random.default_rng(seed)
    h, w = shape
    y, x = np.mgrid[:h, :w]
    rate = 80.0 * rng.integers(-2, 3, shape) + 5e5 * np.exp(-((y - h / 3) ** 2 + (x - w / 2) ** 2) / 20.0)
    radiance = rate.astype(np.float32)
    radiance[rng.random(shape) < 0.01] = np.nan
    variance = (2873.18 + np.maximum(rate, 0) * 3.1).astype(np.float32)
    variance[np.isnan(radiance)] = np.nan
    saturated = rate > 4e5
    variance[saturated] = np.inf
    variance[0, :3] = (-np.inf, np.nan, np.inf)
    count = rng.integers(0, 6, shape).astype(np.uint8)
    return MergeResult(radiance, variance, count, saturated, np.full((2, 2), 4000.0), NoiseModel(1.0, 2.0), "optimal")


def _writer(path, shape, n=3) -> ResultsWriter:
    noise = NoiseModel(1.5, 2.5, "rig")
    return ResultsWriter.create(
        path,
        run_id="r",
        run_file="r.h5",
        n_positions=n,
        frame_shape=shape,
        software_version="t",
        hdr=HDRInfo("optimal", noise, noise, "RGGB"),
    )


def _bit_rounded(a: np.ndarray, mantissa_bits: int = 12) -> np.ndarray:
    """float32 rounded to ``mantissa_bits``, to nearest with ties to even (as
    numcodecs.BitRound), non-finite as +inf: the stored variance's definition in NumPy."""
    a = np.where(np.isfinite(a), a, np.inf).astype(np.float32)
    bits, drop = a.view(np.uint32).copy(), np.uint32(23 - mantissa_bits)
    rounded = (bits + ((bits >> drop) & np.uint32(1)) + np.uint32((1 << (int(drop) - 1)) - 1)) >> drop << drop
    return np.where(np.isfinite(a), rounded, bits).view(np.float32)


def _stored(m: MergeResult) -> dict[str, np.ndarray]:
    return {"radiance": m.radiance, "variance": _bit_rounded(m.variance), "count": m.count, "saturated": m.saturated}


def _assert_bits_equal(a: np.ndarray, b: np.ndarray) -> None:
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape and a.dtype == b.dtype
    assert np.array_equal(
        a.view(f"u{a.itemsize}") if a.dtype.kind == "f" else a, b.view(f"u{b.itemsize}") if b.dtype.kind == "f" else b
    )


def test_c_blosc_runs_on_the_calling_thread_only():
    assert blosc.nthreads == 1


@pytest.mark.parametrize("how", ["write_encoded", "write_hdr"])
def test_results_round_trip_bit_for_bit(tmp_path, how):
    m = _merge()
    path = tmp_path / "r.results.h5"
    with _writer(path, m.radiance.shape) as writer:
        writer.write_encoded(1, encode_hdr(m)) if how == "write_encoded" else writer.write_hdr(1, m)
    with Results.open(path) as results:
        assert results.hdr_done.tolist() == [False, True, False]
        got = {name: getattr(results, name)(1) for name in NAMES}
        with pytest.raises(Exception, match="no HDR result"):
            results.radiance(0)
    expected = _stored(m)
    for name in NAMES:
        _assert_bits_equal(got[name], expected[name])
    # Plain h5py + hdf5plugin, without the project: the same numbers.
    code = (
        "import sys, h5py, hdf5plugin, numpy as np\n"
        "with h5py.File(sys.argv[1], 'r') as f:\n"
        "    np.savez(sys.argv[2], **{k: f['hdr'][k][1] for k in ('radiance', 'variance', 'count', 'saturated')},"
        " unwritten=f['hdr/radiance'][0])\n"
    )
    subprocess.run([sys.executable, "-c", code, str(path), str(tmp_path / "plain.npz")], check=True)
    plain = np.load(tmp_path / "plain.npz")
    for name in NAMES:
        _assert_bits_equal(plain[name], np.asarray(expected[name], dtype=plain[name].dtype))
    assert np.isnan(plain["unwritten"]).all()


def test_both_ways_of_writing_store_the_same_bytes(tmp_path):
    m = _merge(3)
    with _writer(tmp_path / "a.h5", m.radiance.shape) as a, _writer(tmp_path / "b.h5", m.radiance.shape) as b:
        a.write_encoded(2, encode_hdr(m))
        b.write_hdr(2, m)
    with (
        h5py.File(position_file_for(tmp_path / "a.h5", 2)) as a,
        h5py.File(position_file_for(tmp_path / "b.h5", 2)) as b,
    ):
        assert a.attrs["format"] == "mirrorgonio-results-position"
        for name in NAMES:
            assert a[name].id.read_direct_chunk((0, 0)) == b[name].id.read_direct_chunk((0, 0))
            assert hdf5plugin.BLOSC_ID in {int(k) for k in a[name]._filters}


def test_the_results_file_reads_as_whole_arrays_with_plain_h5py(tmp_path, monkeypatch):
    """The index's virtual datasets map each position onto its file, found relative to the
    results file wherever the reader runs; positions never written read as the fill value."""
    m = _merge(4)
    path = tmp_path / "run-7.results.h5"
    with _writer(path, m.radiance.shape) as writer:
        writer.write_encoded(1, encode_hdr(m))
    assert position_file_for(path, 1) == tmp_path / "run-7.hdr" / "position-001.h5"
    assert sorted(p.name for p in (tmp_path / "run-7.hdr").iterdir()) == ["position-001.h5"]  # no temporary left
    monkeypatch.chdir("/")
    with h5py.File(path, "r") as f:
        g = f["hdr"]
        assert g["radiance"].is_virtual and g["radiance"].shape == (3, *m.radiance.shape)
        whole = g["radiance"][:]
        _assert_bits_equal(whole[1], m.radiance)
        assert np.isnan(whole[0]).all() and np.isnan(whole[2]).all()
        assert (g["count"][0] == 0).all() and g["done"][:].tolist() == [0, 1, 0]
        assert np.array_equal(g["saturation_level"][1], m.saturation_level)
    # A copy must carry the index and the done positions' files (the download packs these).
    with Results.open(path) as results:
        assert results.files() == [path, tmp_path / "run-7.hdr" / "position-001.h5"]


def test_a_missing_or_unwritten_position_file_is_one_line(tmp_path):
    m = _merge(6)
    path = tmp_path / "r.results.h5"
    with _writer(path, m.radiance.shape) as writer:
        with pytest.raises(ResultsError, match=r"position 0: .*position-000.h5 was not written"):
            writer.commit_position(0, m.saturation_level)
        writer.write_hdr(2, m)
    position_file_for(path, 2).unlink()
    with Results.open(path) as results:
        with pytest.raises(ResultsError, match=r"position 2: its file .*position-002.h5 is missing"):
            results.radiance(2)
        assert results.hdr_done.tolist() == [False, False, True]


def test_results_written_before_read_the_same(tmp_path):
    """Version-1 files: the data inside the results file, one position per chunk, Blosc LZ4
    byte shuffle for the floats, the LZ4 filter for the masks, written through HDF5's pipeline."""
    m = _merge(5)
    h, w = m.radiance.shape
    path = tmp_path / "old.results.h5"
    with _writer(path, (h, w)) as writer:
        writer.close()
    with h5py.File(path, "r+") as f:
        f.attrs["format_version"] = 1  # the data inside the results file, chunked one position per chunk
        g = f["hdr"]
        blosc_lz4 = dict(hdf5plugin.Blosc(cname="lz4", clevel=5, shuffle=hdf5plugin.Blosc.SHUFFLE))
        for name, dtype, options in (
            ("radiance", "f4", dict(fillvalue=np.nan, **blosc_lz4)),
            ("variance", "f4", dict(fillvalue=np.nan, **blosc_lz4)),
            ("count", "u1", dict(hdf5plugin.LZ4())),
            ("saturated", "u1", dict(hdf5plugin.LZ4())),
        ):
            del g[name]
            g.create_dataset(name, (3, h, w), dtype, chunks=(1, h, w), **options)
        for name, array in _stored(m).items():
            g[name][0] = array
        noise = np.random.default_rng(0).integers(0, 2**32, (h, w), dtype=np.uint32).view(np.float32)
        g["radiance"][1] = noise  # a chunk Blosc gives up on is stored as it is (filter mask 1)
        assert g["radiance"].id.get_chunk_info_by_coord((1, 0, 0)).filter_mask != 0
        g["done"][:2] = 1
    with Results.open(path) as results:
        for name, array in _stored(m).items():
            _assert_bits_equal(getattr(results, name)(0), np.asarray(array))
        _assert_bits_equal(results.radiance(1), noise)
        assert results.files() == [path]  # everything inside


def test_the_stored_variance_keeps_12_mantissa_bits_rounded_to_nearest():
    rng = np.random.default_rng(11)
    variance = (10.0 ** rng.uniform(2, 9, 50_000)).astype(np.float32)
    variance[:4] = (np.nan, -np.inf, np.inf, 0.0)
    stored = stored_variance(variance)
    _assert_bits_equal(stored, _bit_rounded(variance))
    assert stored[:4].tolist() == [np.inf, np.inf, np.inf, 0.0]
    relative = np.abs(stored[4:] / variance[4:] - 1.0)
    assert relative.max() <= 2.0**-13 and relative.max() > 2.0**-14  # to nearest, not truncated
    assert abs(np.mean(stored[4:] / variance[4:] - 1.0)) < 1e-6  # unbiased
    # Ties go to the even neighbour: 1 + 2⁻¹³ and 1 + 3·2⁻¹³ sit halfway between kept values.
    ties = np.array([1 + 2.0**-13, 1 + 3 * 2.0**-13], np.float32)
    assert stored_variance(ties).tolist() == [1.0, 1 + 4 * 2.0**-13]
    _assert_bits_equal(stored_variance(stored), stored)  # once is enough
    _assert_bits_equal(stored_variance(variance.astype(np.float64)), stored)
    in_place = variance.copy()
    assert stored_variance(in_place, out=in_place) is in_place
    _assert_bits_equal(in_place, stored)
    with pytest.raises(ValueError, match="out must be C-contiguous float32"):
        stored_variance(variance, out=np.empty(variance.shape))


def test_the_rounded_variance_compresses_to_less_than_half():
    """A mirror-ball position as the merge leaves it: mostly dark noise, a few bright blobs,
    five exposures. The variances take a few thousand distinct values at random across the
    frame; their low mantissa bits are what a compressor cannot squeeze. Rounded away, the
    chunk is less than half the size (3.1 MB instead of 7.9 on a simulated 1312×2000 position)."""
    rng = np.random.default_rng(12)
    h, w, black, white = 512, 768, 64, 4095  # the default rig's 12-bit camera
    exposures = np.array([2e-5, 1e-4, 5e-4, 2.5e-3, 1.25e-2])
    y, x = np.mgrid[:h, :w]
    rate_e = 2e8 * np.exp(-((y - 200.0) ** 2 + (x - 300.0) ** 2) / 50.0) + 4e6 * np.exp(
        -((y - 350.0) ** 2 + (x - 500.0) ** 2) / 400.0
    )
    gain, read = (
        20000 / (white - black),
        3.0 / (20000 / (white - black)),
    )  # e⁻/DN, DN: 20 ke⁻ full well, 3 e⁻ read noise
    frames = np.stack([rng.poisson(rate_e * t) / gain + rng.normal(black, read, (h, w)) for t in exposures])
    frames = np.clip(np.round(frames), 0, white).astype(np.uint16)
    m = merge_raw(frames, exposures, black, white, NoiseModel(gain, read))
    rounded = len(encode_hdr(m).chunks["variance"][1])
    unrounded = len(
        blosc.compress(
            np.where(np.isfinite(m.variance), m.variance, np.inf).astype(np.float32),
            typesize=4,
            clevel=1,
            shuffle=blosc.SHUFFLE,
            cname="blosclz",
        )
    )
    assert rounded < 0.5 * unrounded, (rounded, unrounded)  # 0.42 here


def test_encoded_chunks_are_smaller_than_the_arrays():
    m = _merge(1, shape=(256, 384))
    encoded = encode_hdr(m)
    assert encoded.shape == m.radiance.shape
    for name, (mask, data) in encoded.chunks.items():
        assert mask == 0 and len(data) < _stored(m)[name].nbytes


# --- images ---------------------------------------------------------------------------------------
def _rgb(seed=0, shape=(66, 100)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    rgb = (np.round(rng.normal(0.0, 2.0, (*shape, 3))) * 20.0).astype(np.float32)
    y, x = np.mgrid[: shape[0], : shape[1]]
    rgb += (3e5 * np.exp(-((y - shape[0] / 2) ** 2 + (x - shape[1] / 3) ** 2) / 30.0))[..., None].astype(np.float32)
    return rgb


def _reference_tonemap(rgb: np.ndarray, percentile: float = 99.9) -> np.ndarray:
    """The tone mapping in plain NumPy: the definition the one-pass kernel meets."""
    finite = np.nan_to_num(rgb, nan=0.0, posinf=0.0, neginf=0.0)
    sample = finite[::4, ::4] if finite.shape[0] * finite.shape[1] > 250_000 else finite
    scale = float(np.percentile(sample, percentile))
    if scale <= 0:
        scale = max(float(finite.max()), 1e-30)
    with np.errstate(over="ignore"):
        return (np.sqrt(np.clip(finite / scale, 0.0, 1.0)) * 255.0 + 0.5).astype(np.uint8)


@pytest.mark.parametrize("shape", [(1, 1), (3, 5), (66, 100), (656, 1000)])
def test_exr_is_lossless_float32_rgb_with_non_finite_as_zero(tmp_path, shape):
    rgb = _rgb(1, shape)
    rgb.flat[::7] = np.nan
    rgb.flat[1::11] = np.inf
    rgb.flat[2::13] = -np.inf
    path = write_exr(tmp_path / "a.exr", rgb)
    back = read_exr(path)
    _assert_bits_equal(back, np.nan_to_num(rgb, nan=0.0, posinf=0.0, neginf=0.0))
    with OpenEXR.File(str(path)) as exr:
        header = exr.header()
        assert header["compression"] == OpenEXR.NO_COMPRESSION
        assert exr.channels()["RGB"].pixels.dtype == np.float32
        assert tuple(header["dataWindow"][1]) == (shape[1] - 1, shape[0] - 1)


@pytest.mark.parametrize("compression", ["piz", "zip", "rle"])
def test_exr_compressions_through_openexr_stay_lossless(tmp_path, compression):
    rgb = _rgb(2).astype(np.float64)
    rgb[0, 0] = np.nan
    back = read_exr(write_exr(tmp_path / "a.exr", rgb, compression=compression))
    _assert_bits_equal(back, np.nan_to_num(rgb, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32))
    with pytest.raises(ValueError, match="EXR compression: 'dwaa' is not one of"):
        write_exr(tmp_path / "b.exr", rgb, compression="dwaa")


def test_tonemap_matches_the_numpy_definition_exactly():
    rng = np.random.default_rng(7)
    cases = [_rgb(3), _rgb(4, (560, 500)), np.zeros((4, 4, 3), np.float32), np.full((3, 3, 3), -2.0, np.float32)]
    for seed in range(30):
        h, w = rng.integers(1, 30, 2)
        x = (rng.normal(size=(h, w, 3)) * 10 ** rng.uniform(-6, 6)).astype(np.float32)
        if seed % 3 == 0:
            x[rng.random(x.shape) < 0.2] = np.nan
            x[rng.random(x.shape) < 0.05] = np.inf
            x[rng.random(x.shape) < 0.05] = -np.inf
        if seed % 3 == 1:
            x = np.round(x)
        cases.append(x)
    for x in cases:
        assert np.array_equal(tonemap(x), _reference_tonemap(x))


def test_png_is_the_tone_mapped_image(tmp_path):
    rgb = _rgb(5)
    path = write_png(tmp_path / "a.png", rgb)
    with Image.open(path) as im:
        im.verify()  # chunk CRCs
    decoded = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(decoded[..., ::-1], _reference_tonemap(rgb))


@pytest.mark.parametrize("shape", [(1, 1), (1, 7), (5, 1), (33, 47), (656, 1000)])
def test_encoded_png_decodes_to_the_same_pixels_in_pillow_and_opencv(shape):
    rng = np.random.default_rng(sum(shape))
    image = rng.integers(0, 256, (*shape, 3), dtype=np.uint8)
    image[: shape[0] // 2] //= 16  # some structure for the deflate, and some noise
    data = encode_png(image)
    with Image.open(io.BytesIO(data)) as im:
        assert im.mode == "RGB" and im.size == (shape[1], shape[0])
        assert np.array_equal(np.asarray(im), image)
    with Image.open(io.BytesIO(data)) as im:
        im.verify()  # every chunk's CRC
    decoded = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(decoded[..., ::-1], image)


@pytest.mark.parametrize(
    "bad",
    [
        np.zeros((4, 4, 3), np.uint16),
        np.zeros((4, 4), np.uint8),
        np.zeros((4, 4, 4), np.uint8),
        np.zeros((0, 4, 3), np.uint8),
    ],
)
def test_encode_png_refuses_what_is_not_8_bit_rgb(bad):
    with pytest.raises(ValueError, match=r"\(H, W, 3\) uint8"):
        encode_png(bad)


def test_a_wide_png_is_resized_to_the_preview_width(tmp_path):
    rgb = _rgb(6, (300, 1500))
    decoded = cv2.imread(str(write_png(tmp_path / "a.png", rgb)), cv2.IMREAD_UNCHANGED)
    expected = cv2.resize(_reference_tonemap(rgb), (1000, 200), interpolation=cv2.INTER_AREA)
    assert np.array_equal(decoded[..., ::-1], expected)
