"""The results file: what the processing derives from one run, beside the run file.

One module defines it (``docs/results-file.md``). It is written position by position, so
a run is never loaded whole and an interrupted processing keeps what it finished.

Each position's merge lives in its own small HDF5 file, ``RUN.hdr/position-NNN.h5``,
compressed and written where the position was merged (:func:`encode_hdr` and
:func:`write_position_file`, in a worker process); ``RUN.results.h5`` holds the index:
virtual datasets ``/hdr/radiance`` ... of shape (n, H, W) that map position ``i`` onto its
file (so plain h5py reads the whole run as one array), and the per-position metadata with
the ``done`` flags, written by the one process that owns the file
(:meth:`ResultsWriter.commit_position`). The merged data thus never travels between
processes: with one process per core, receiving and writing ~10 MB a position in the
coordinating process took half a core away from the workers (format version 2; version 1
kept the data inside the results file, and still reads).
"""

from __future__ import annotations

import os
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import blosc
import h5py
import hdf5plugin
import numba
import numpy as np
from numpy.typing import ArrayLike

from processing.hdr.model import MergeResult, NoiseModel

RESULTS_FORMAT = "mirrorgonio-results"
RESULTS_VERSION = 2
POSITION_FORMAT = "mirrorgonio-results-position"
_FILL = {"radiance": np.nan, "variance": np.nan, "count": 0, "saturated": 0}
#: How to read the data with plain h5py, in the files themselves (``/hdr`` and each position
#: file carry it as their ``reading`` attribute): Blosc is not one of HDF5's built-in filters.
READING = (
    "the datasets are compressed with Blosc LZ4 (HDF5 filter 32001): `import hdf5plugin` before h5py reads them, "
    "or set HDF5_PLUGIN_PATH to hdf5plugin.PLUGIN_PATH for any HDF5 program (docs/results-file.md)"
)


class ResultsError(ValueError):
    """An unreadable or foreign results file (one line naming the file)."""


#: The suffixes a run file's name may end with that are not part of the run's name.
RUN_FILE_SUFFIXES = (".h5", ".hdf5", ".hdf")


def run_name(run_path: str | Path) -> str:
    """The name a run's outputs are named after: the run file's whole name without its HDF5 suffix.

    Only ``.h5`` (``.hdf5``, ``.hdf``) is dropped, so that runs whose names differ after a dot
    keep distinct outputs.

    Examples
    --------
    >>> run_name("data/yaw-0.05.h5"), run_name("a.1.hdf5"), run_name("run-7")
    ('yaw-0.05', 'a.1', 'run-7')
    """
    name = Path(run_path).name
    for suffix in RUN_FILE_SUFFIXES:
        if name.lower().endswith(suffix) and len(name) > len(suffix):
            return name[: -len(suffix)]
    return name


def results_path_for(run_path: str | Path, out_dir: str | Path | None = None) -> Path:
    """``RUN.results.h5`` beside the run, or in ``out_dir`` (``RUN``: :func:`run_name`)."""
    run_path = Path(run_path)
    folder = Path(out_dir) if out_dir is not None else run_path.parent
    return folder / f"{run_name(run_path)}.results.h5"


def _stem(results_path: Path) -> str:
    name = results_path.name
    return name[: -len(".results.h5")] if name.endswith(".results.h5") else results_path.stem


def position_file_name(results_path: str | Path, index: int) -> str:
    """Position ``index``'s file relative to the results file's folder:
    ``RUN.hdr/position-NNN.h5`` (beside that position's EXR and PNG)."""
    return f"{_stem(Path(results_path))}.hdr/position-{index:03d}.h5"


def position_file_for(results_path: str | Path, index: int) -> Path:
    """The path of position ``index``'s file (:func:`position_file_name`)."""
    return Path(results_path).parent / position_file_name(results_path, index)


@dataclass(frozen=True)
class _Codec:
    """How one per-position dataset is compressed: Blosc (HDF5 filter 32001, ``hdf5plugin``)
    with these settings, the chunk compressed by c-blosc itself (python-blosc), so that a
    position is compressed without HDF5 (:func:`encode_hdr`).

    python-blosc, not its successor blosc2, because filter 32001 reads Blosc1 chunks
    (format version 2) and blosc2 writes format 5, which that filter refuses (HDF5's Blosc2
    filter, 32026, takes a 2-D chunk as a b2nd frame, not as a plain chunk: another file
    format). Compressing through HDF5's own filter instead (h5py with ``hdf5plugin``, an
    in-memory file, the chunk read back) makes the same bytes but took 24 ms a position
    against 14.5 ms here (1312x2000, one core, median of 20).

    The blocksize is Blosc's unit of work, stored in each chunk's header: any reader decodes
    it whatever it is."""

    cname: Literal["blosclz", "lz4", "lz4hc", "snappy", "zlib", "zstd"]
    clevel: int
    shuffle: int  # blosc.NOSHUFFLE, SHUFFLE (byte) or BITSHUFFLE
    blocksize: int

    def filter(self) -> dict[str, Any]:
        return dict(hdf5plugin.Blosc(cname=self.cname, clevel=self.clevel, shuffle=self.shuffle))

    def encode(self, array: np.ndarray) -> bytes:
        array = np.ascontiguousarray(array)
        with _blosc_lock:  # the blocksize is c-blosc's global setting
            blosc.set_blocksize(self.blocksize)
            return blosc.compress(
                array, typesize=array.itemsize, clevel=self.clevel, shuffle=self.shuffle, cname=self.cname
            )


# One worker process per core: c-blosc must not start threads of its own (python-blosc
# asks for one per core when imported). The GIL is let go while it compresses.
blosc.set_nthreads(1)
blosc.set_releasegil(True)
_blosc_lock = threading.Lock()

#: Chosen by measurement on a 1312x2000 mirror-ball position (~4 % lit, the rest dark noise
#: quantised by the merge), one core: compress / decompress ms and MB of 10.5 MB.
#: Radiance: bit-shuffled LZ4 in 64 KiB blocks, 5 / 3 ms, 1.8 MB (byte-shuffled LZ4: 10 / 4 ms,
#: 2.9 MB). Variance, rounded to 12 mantissa bits (:func:`stored_variance`): bit-shuffled LZ4 in
#: 64 KiB blocks, 4.6 ms, 3.1 MB (unrounded, byte-shuffled BloscLZ: 4.1 ms, 7.9 MB; bit-shuffled
#: LZ4: 7 ms, 6.3 MB). Every MB written costs ~2 ms on a VM whose freed memory goes back to its
#: host. The masks: LZ4, 0.3 / 0.1 ms, < 40 kB.
_CODECS = {
    "radiance": _Codec("lz4", 5, blosc.BITSHUFFLE, 64 * 1024),
    "variance": _Codec("lz4", 5, blosc.BITSHUFFLE, 64 * 1024),
    "count": _Codec("lz4", 5, blosc.NOSHUFFLE, 256 * 1024),
    "saturated": _Codec("lz4", 5, blosc.NOSHUFFLE, 256 * 1024),
}


def _position_datasets() -> dict[str, tuple[str, dict]]:
    """The per-position datasets of ``/hdr``: dtype and creation options (chunks aside)."""
    fill = {"radiance": np.nan, "variance": np.nan, "count": 0, "saturated": 0}
    dtypes = {"radiance": "f4", "variance": "f4", "count": "u1", "saturated": "u1"}
    return {name: (dtypes[name], dict(fillvalue=fill[name], **codec.filter())) for name, codec in _CODECS.items()}


#: Mantissa bits kept of each stored variance (float32 has 23): relative rounding error at
#: most 2⁻¹³ = 1.2e-4. A variance computed from one noisy sample is itself uncertain by
#: ~√(2/N) for N electrons (0.3 % at 10⁵ e⁻, the most a merged pixel holds here), so the
#: dropped bits are noise; zeroing them lets the variance compress to 3.1 MB instead of
#: 7.9 MB a 1312×2000 position (bit rounding: Klöwer et al. 2021, "Compressing atmospheric
#: data into its real information content", Nat. Comput. Sci. 1, 713; ``numcodecs.BitRound``).
VARIANCE_MANTISSA_BITS = 12


@numba.njit(cache=True)
def _round_bits_in_place(bits, dropped_bits):
    """Float32 values, seen as their uint32 ``bits``, as stored: non-finite ones as +inf, the
    lowest ``dropped_bits`` mantissa bits rounded away to nearest, ties to even (as
    ``numcodecs.BitRound``). Integer operations on one array only, which the compiler
    vectorizes: 0.56 ms a 1312×2000 variance, in place, where the same rounding done on the
    floats and their bits as two views of one array takes 1.9 ms."""
    shift = np.uint32(dropped_bits)
    half = np.uint32((1 << (dropped_bits - 1)) - 1)
    keep = np.uint32(~((1 << dropped_bits) - 1) & 0xFFFFFFFF)
    exponent = np.uint32(0x7F800000)  # all ones: inf or nan; +inf is exactly this
    b = bits.ravel()
    for i in range(b.size):
        x = b[i]
        if (x & exponent) == exponent:
            b[i] = exponent
        else:
            b[i] = (x + ((x >> shift) & np.uint32(1)) + half) & keep
    return bits


def stored_variance(variance: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Variances as the results file stores them: float32 rounded to
    :data:`VARIANCE_MANTISSA_BITS` mantissa bits, non-finite ones as +inf. Into ``out``
    (a C-contiguous float32 array of the same shape, which may be ``variance`` itself), else
    a new array; applying it twice changes nothing more."""
    variance = np.ascontiguousarray(variance)
    if variance.dtype.kind != "f":
        variance = variance.astype(np.float64)
    if out is None:
        out = np.empty(variance.shape, np.float32)
    elif out.dtype != np.float32 or out.shape != variance.shape or not out.flags.c_contiguous:
        raise ValueError(f"stored_variance: out must be C-contiguous float32 of shape {variance.shape}")
    if out is not variance:
        with np.errstate(over="ignore"):  # past float32's range: +inf, as stored
            np.copyto(out, variance, casting="same_kind")
    _round_bits_in_place(out.view(np.uint32), 23 - VARIANCE_MANTISSA_BITS)
    return out


def _position_arrays(result: MergeResult, variance_stored: bool) -> dict[str, np.ndarray]:
    """A merge as the results file stores it (variances rounded, non-finite ones as +inf)."""
    saturated = np.asarray(result.saturated)
    return {
        "radiance": np.asarray(result.radiance, dtype=np.float32),
        "variance": result.variance if variance_stored else stored_variance(result.variance),
        "count": np.asarray(result.count, dtype=np.uint8),
        "saturated": saturated.view(np.uint8) if saturated.dtype == bool else saturated.astype(np.uint8),
    }


@dataclass
class EncodedHDR:
    """One position's merge as the results file's compressed chunks: ``chunks`` maps each
    per-position dataset to (HDF5 filter mask, chunk bytes)."""

    chunks: dict[str, tuple[int, bytes]]
    saturation_level: np.ndarray
    shape: tuple[int, int]


def encode_hdr(result: MergeResult, *, variance_stored: bool = False) -> EncodedHDR:
    """Compress one position's merge as :class:`ResultsWriter` stores it: one chunk per
    dataset, compressed by c-blosc directly (no HDF5), with each dataset's filter settings.
    ``variance_stored``: ``result.variance`` already went through :func:`stored_variance`
    (as the position task leaves it), so it is not rounded a second time.

    :meth:`ResultsWriter.write_hdr` writes these very chunks too, so a file holds the same
    bytes whichever way a position was written.
    """
    h, w = result.radiance.shape
    arrays = _position_arrays(result, variance_stored)
    chunks = {name: (0, _CODECS[name].encode(array)) for name, array in arrays.items()}
    return EncodedHDR(chunks, np.asarray(result.saturation_level, float), (h, w))


def write_position_file(path: str | Path, encoded: EncodedHDR) -> Path:
    """Write one position's encoded merge as its own HDF5 file (:func:`position_file_for`):
    the four datasets, one chunk each, written as they are (no re-compression), and its
    saturation level. Written under a temporary name and renamed into place, so a reader
    finds the whole file or none."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
    h, w = encoded.shape
    try:
        with h5py.File(tmp, "w") as f:
            f.attrs.update(format=POSITION_FORMAT, format_version=RESULTS_VERSION, reading=READING)
            for name, (dtype, options) in _position_datasets().items():
                dset = f.create_dataset(name, (h, w), dtype, chunks=(h, w), **options)
                mask, data = encoded.chunks[name]
                dset.id.write_direct_chunk((0, 0), data, mask)
            f.create_dataset("saturation_level", data=np.asarray(encoded.saturation_level, float))
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


@dataclass(frozen=True)
class HDRInfo:
    method: str
    noise: NoiseModel
    rig_noise: NoiseModel
    cfa_pattern: str


class ResultsWriter:
    """Create or extend a results file and write merged positions into it."""

    def __init__(self, path: Path, f: h5py.File):
        self.path = path
        self._f = f

    @classmethod
    def create(
        cls,
        path: str | os.PathLike[str],
        *,
        run_id: str,
        run_file: str,
        n_positions: int,
        frame_shape: tuple[int, int],
        software_version: str,
        hdr: HDRInfo,
    ) -> ResultsWriter:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp")
        h, w = frame_shape
        with h5py.File(tmp, "w") as f:
            f.attrs.update(
                format=RESULTS_FORMAT,
                format_version=RESULTS_VERSION,
                run_id=run_id,
                run_file=str(run_file),
                software_version=software_version,
            )
            g = f.create_group("hdr")
            g.attrs.update(
                method=hdr.method,
                cfa_pattern=hdr.cfa_pattern,
                units="DN/s above black, per Bayer site",
                reading=READING,
                gain_e_per_dn=hdr.noise.gain_e_per_dn,
                read_noise_dn=hdr.noise.read_noise_dn,
                noise_source=hdr.noise.source,
                rig_gain_e_per_dn=hdr.rig_noise.gain_e_per_dn,
                rig_read_noise_dn=hdr.rig_noise.read_noise_dn,
            )
            for name, (dtype, _options) in _position_datasets().items():
                layout = h5py.VirtualLayout((n_positions, h, w), dtype)
                for i in range(n_positions):
                    layout[i] = h5py.VirtualSource(position_file_name(path, i), name, shape=(h, w))
                g.create_virtual_dataset(name, layout, fillvalue=_FILL[name])
            g.create_dataset("saturation_level", data=np.full((n_positions, 2, 2), np.nan))
            g.create_dataset("done", data=np.zeros(n_positions, dtype="u1"))
        tmp.replace(path)
        return cls(path, h5py.File(path, "r+"))

    def write_hdr(self, index: int, result: MergeResult) -> None:
        """Write one position's merge (compressed here, as :func:`encode_hdr` does)."""
        self.write_encoded(index, encode_hdr(result))

    def write_encoded(self, index: int, encoded: EncodedHDR) -> None:
        """Write one position compressed elsewhere (:func:`encode_hdr`): its file, then commit it."""
        self._check_shape(index, encoded.shape)
        self._f["hdr"]["done"][index] = 0
        write_position_file(position_file_for(self.path, index), encoded)
        self.commit_position(index, encoded.saturation_level)

    def commit_position(self, index: int, saturation_level: ArrayLike | None) -> None:
        """Record a position whose file was written elsewhere (:func:`write_position_file`,
        by a worker): its saturation level, then its ``done`` flag."""
        source = position_file_for(self.path, index)
        if not source.is_file():
            raise ResultsError(f"{self.path}: position {index}: {source} was not written")
        self._f["hdr"]["saturation_level"][index] = np.asarray(saturation_level, float)
        self._commit(index)

    def _check_shape(self, index: int, shape: tuple[int, ...]) -> None:
        held = tuple(self._f["hdr"]["radiance"].shape[1:])
        if tuple(shape) != held:
            raise ResultsError(f"{self.path}: position {index} is {tuple(shape)}, the file holds {held}")

    def _commit(self, index: int) -> None:
        self._f.flush()
        self._f["hdr"]["done"][index] = 1  # the commit flag, written last
        self._f.flush()

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> ResultsWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _read_blosc_chunk(dset: h5py.Dataset, index: int | None = None) -> np.ndarray | None:
    """Position ``index`` of a one-position-per-chunk dataset (or, with no index, a
    single-chunk dataset) whose only filter is Blosc, decompressed by c-blosc straight into
    the array; None when the dataset or chunk is not so (the caller reads it through HDF5).

    Measured on a 1312x2000 position file (6.5 MB, its four datasets), one core, median of
    30: 9.6 ms decompressed here, 13.9 ms through h5py and ``hdf5plugin`` (the HDF5
    pipeline's copies), 8.2 ms by blosc2's ``decompress2`` (which reads these Blosc1
    chunks, but cannot write them: :class:`_Codec`), not worth a second Blosc library."""
    shape = dset.shape[1:] if index is not None else dset.shape
    coords = (index, *(0 for _ in shape)) if index is not None else tuple(0 for _ in shape)
    if dset.chunks != ((1, *shape) if index is not None else shape):
        return None
    plist = dset.id.get_create_plist()
    if plist.get_nfilters() != 1 or plist.get_filter(0)[0] != hdf5plugin.BLOSC_ID:
        return None
    info = dset.id.get_chunk_info_by_coord(coords)
    if info.byte_offset is None or info.filter_mask != 0:  # never written, or stored as it is
        return None
    _, chunk = dset.id.read_direct_chunk(coords)
    out = np.empty(shape, dset.dtype)
    if blosc.get_cbuffer_sizes(chunk)[0] != out.nbytes:
        return None
    blosc.decompress_ptr(chunk, out.ctypes.data)
    return out


class Results:
    """Read a results file."""

    def __init__(self, path: Path, f: h5py.File):
        self.path, self._f = path, f

    @classmethod
    def open(cls, path: str | os.PathLike[str]) -> Results:
        path = Path(path)
        try:
            f = h5py.File(path, "r")
        except FileNotFoundError:
            raise ResultsError(f"{path}: results file not found") from None
        except OSError as exc:
            raise ResultsError(f"{path}: not a readable HDF5 file ({exc})") from None
        if f.attrs.get("format") != RESULTS_FORMAT:
            f.close()
            raise ResultsError(f"{path}: not a mirrorgonio results file")
        if int(f.attrs.get("format_version", 0)) > RESULTS_VERSION:
            f.close()
            raise ResultsError(
                f"{path}: results format version {f.attrs['format_version']} is newer than this software "
                f"reads ({RESULTS_VERSION})"
            )
        return cls(path, f)

    def __enter__(self) -> Results:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._f.close()

    @property
    def hdr_done(self) -> np.ndarray:
        return self._f["hdr/done"][:].astype(bool)

    def files(self) -> list[Path]:
        """Every file the results' data live in: this one, then (format version 2) the done
        positions' files in position order. What a copy of the results must carry, at the
        same paths relative to this file's folder (:func:`position_file_name`)."""
        if "hdr/radiance" not in self._f or not self._f["hdr/radiance"].is_virtual:
            return [self.path]
        return [self.path] + [position_file_for(self.path, int(i)) for i in np.flatnonzero(self.hdr_done)]

    @property
    def noise(self) -> NoiseModel:
        a = self._f["hdr"].attrs
        return NoiseModel(float(a["gain_e_per_dn"]), float(a["read_noise_dn"]), str(a["noise_source"]))

    @property
    def cfa_pattern(self) -> str:
        return str(self._f["hdr"].attrs["cfa_pattern"])

    def _position(self, name: str, index: int) -> np.ndarray:
        if not self.hdr_done[index]:
            raise ResultsError(f"{self.path}: position {index} has no HDR result")
        dset = self._f["hdr"][name]
        if dset.is_virtual:
            return self._from_position_file(name, index)
        fast = _read_blosc_chunk(dset, index)  # format version 1: the data inside
        return fast if fast is not None else dset[index]

    def _from_position_file(self, name: str, index: int) -> np.ndarray:
        source = position_file_for(self.path, index)
        try:
            with h5py.File(source, "r") as f:
                dset = f[name]
                fast = _read_blosc_chunk(dset)
                return fast if fast is not None else dset[()]
        except FileNotFoundError:
            raise ResultsError(f"{self.path}: position {index}: its file {source} is missing") from None
        except (OSError, KeyError) as exc:
            raise ResultsError(f"{self.path}: position {index}: {source} is unreadable ({exc})") from None

    def radiance(self, index: int) -> np.ndarray:
        return self._position("radiance", index)

    def variance(self, index: int) -> np.ndarray:
        return self._position("variance", index)

    def count(self, index: int) -> np.ndarray:
        return self._position("count", index)

    def saturated(self, index: int) -> np.ndarray:
        return self._position("saturated", index).astype(bool)
