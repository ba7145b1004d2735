"""The results file: what the processing derives from one run, beside the run file.

One module defines it (``docs/results-file.md``). It is written position by position, so
a run is never loaded whole and an interrupted processing keeps what it finished.

The per-position datasets are chunked one position per chunk, so a position can be
compressed where it was merged (:func:`encode_hdr`, in a worker process) and the chunks
written as they are by the one process that writes the file
(:meth:`ResultsWriter.write_encoded`): the file's writer only copies bytes.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import h5py
import hdf5plugin
import numpy as np

from processing.hdr import MergeResult, NoiseModel

RESULTS_FORMAT = "mirrorgonio-results"
RESULTS_VERSION = 1


class ResultsError(ValueError):
    """An unreadable or foreign results file (one line naming the file)."""


def results_path_for(run_path: str | Path, out_dir: str | Path | None = None) -> Path:
    """``RUN.results.h5`` beside the run, or in ``out_dir``."""
    run_path = Path(run_path)
    folder = Path(out_dir) if out_dir is not None else run_path.parent
    return folder / f"{run_path.stem}.results.h5"


def _float_filter() -> dict:
    # Byte-shuffled LZ4 in Blosc: floats compress well, and fast.
    return dict(hdf5plugin.Blosc(cname="lz4", clevel=5, shuffle=hdf5plugin.Blosc.SHUFFLE))


def _position_datasets() -> dict[str, tuple[str, dict]]:
    """The per-position datasets of ``/hdr``: dtype and creation options (chunks aside)."""
    return {
        "radiance": ("f4", dict(fillvalue=np.nan, **_float_filter())),
        "variance": ("f4", dict(fillvalue=np.nan, **_float_filter())),
        "count": ("u1", dict(hdf5plugin.LZ4())),
        "saturated": ("u1", dict(hdf5plugin.LZ4())),
    }


def _position_arrays(result: MergeResult) -> dict[str, np.ndarray]:
    """A merge as the results file stores it (non-finite variances as +inf)."""
    return {
        "radiance": result.radiance,
        "variance": np.where(np.isfinite(result.variance), result.variance, np.inf).astype("f4"),
        "count": result.count,
        "saturated": result.saturated.astype("u1"),
    }


@dataclass
class EncodedHDR:
    """One position's merge as the results file's compressed chunks: ``chunks`` maps each
    per-position dataset to (HDF5 filter mask, chunk bytes)."""

    chunks: dict[str, tuple[int, bytes]]
    saturation_level: np.ndarray
    shape: tuple[int, int]


def encode_hdr(result: MergeResult) -> EncodedHDR:
    """Compress one position's merge exactly as :class:`ResultsWriter` would store it.

    The datasets are made with the same filters and one-position chunks in an in-memory
    HDF5 file, and their chunk read back raw: written with
    :meth:`ResultsWriter.write_encoded`, the file holds the same bytes as with
    :meth:`ResultsWriter.write_hdr`.
    """
    arrays = _position_arrays(result)
    h, w = result.radiance.shape
    chunks = {}
    with h5py.File(f"encode-{id(result)}", "w", driver="core", backing_store=False) as f:
        for name, (dtype, options) in _position_datasets().items():
            dset = f.create_dataset(name, (1, h, w), dtype, chunks=(1, h, w), **options)
            dset[0] = arrays[name]
            chunks[name] = dset.id.read_direct_chunk((0, 0, 0))
    return EncodedHDR(chunks, np.asarray(result.saturation_level, float), (h, w))


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
    def create(cls, path, *, run_id: str, run_file: str, n_positions: int, frame_shape: tuple[int, int],
               software_version: str, hdr: HDRInfo) -> ResultsWriter:  # fmt: skip
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp")
        h, w = frame_shape
        with h5py.File(tmp, "w") as f:
            f.attrs.update(format=RESULTS_FORMAT, format_version=RESULTS_VERSION, run_id=run_id,
                           run_file=str(run_file), software_version=software_version)  # fmt: skip
            g = f.create_group("hdr")
            g.attrs.update(
                method=hdr.method, cfa_pattern=hdr.cfa_pattern, units="DN/s above black, per Bayer site",
                gain_e_per_dn=hdr.noise.gain_e_per_dn, read_noise_dn=hdr.noise.read_noise_dn,
                noise_source=hdr.noise.source, rig_gain_e_per_dn=hdr.rig_noise.gain_e_per_dn,
                rig_read_noise_dn=hdr.rig_noise.read_noise_dn,
            )  # fmt: skip
            for name, (dtype, options) in _position_datasets().items():
                g.create_dataset(name, (n_positions, h, w), dtype, chunks=(1, h, w), **options)
            g.create_dataset("saturation_level", data=np.full((n_positions, 2, 2), np.nan))
            g.create_dataset("done", data=np.zeros(n_positions, dtype="u1"))
        tmp.replace(path)
        return cls(path, h5py.File(path, "r+"))

    def write_hdr(self, index: int, result: MergeResult) -> None:
        """Write one position's merge (compressed here)."""
        g = self._f["hdr"]
        g["done"][index] = 0
        for name, array in _position_arrays(result).items():
            g[name][index] = array
        g["saturation_level"][index] = result.saturation_level
        self._commit(index)

    def write_encoded(self, index: int, encoded: EncodedHDR) -> None:
        """Write one position compressed elsewhere (:func:`encode_hdr`): its chunks as they are."""
        g = self._f["hdr"]
        if tuple(encoded.shape) != tuple(g["radiance"].shape[1:]):
            raise ResultsError(f"{self.path}: position {index} is {encoded.shape}, the file holds {g['radiance'].shape[1:]}")
        g["done"][index] = 0
        for name, (mask, data) in encoded.chunks.items():
            g[name].id.write_direct_chunk((index, 0, 0), data, mask)
        g["saturation_level"][index] = encoded.saturation_level
        self._commit(index)

    def _commit(self, index: int) -> None:
        self._f.flush()
        self._f["hdr"]["done"][index] = 1  # the commit flag, written last
        self._f.flush()

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> ResultsWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class Results:
    """Read a results file."""

    def __init__(self, path: Path, f: h5py.File):
        self.path, self._f = path, f

    @classmethod
    def open(cls, path) -> Results:
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
            raise ResultsError(f"{path}: results format version {f.attrs['format_version']} is newer than this software reads ({RESULTS_VERSION})")
        return cls(path, f)

    def __enter__(self) -> Results:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._f.close()

    @property
    def hdr_done(self) -> np.ndarray:
        return self._f["hdr/done"][:].astype(bool)

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
        return self._f["hdr"][name][index]

    def radiance(self, index: int) -> np.ndarray:
        return self._position("radiance", index)

    def variance(self, index: int) -> np.ndarray:
        return self._position("variance", index)

    def count(self, index: int) -> np.ndarray:
        return self._position("count", index)

    def saturated(self, index: int) -> np.ndarray:
        return self._position("saturated", index).astype(bool)
