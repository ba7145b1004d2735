"""The results file: what the processing derives from one run, beside the run file.

One module defines it (``docs/results-file.md``). It is written position by position, so
a run is never loaded whole and an interrupted processing keeps what it finished.
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
            chunks = (1, h, w)
            g.create_dataset("radiance", (n_positions, h, w), "f4", chunks=chunks, fillvalue=np.nan, **_float_filter())
            g.create_dataset("variance", (n_positions, h, w), "f4", chunks=chunks, fillvalue=np.nan, **_float_filter())
            g.create_dataset("count", (n_positions, h, w), "u1", chunks=chunks, **hdf5plugin.LZ4())
            g.create_dataset("saturated", (n_positions, h, w), "u1", chunks=chunks, **hdf5plugin.LZ4())
            g.create_dataset("saturation_level", data=np.full((n_positions, 2, 2), np.nan))
            g.create_dataset("done", data=np.zeros(n_positions, dtype="u1"))
        tmp.replace(path)
        return cls(path, h5py.File(path, "r+"))

    def write_hdr(self, index: int, result: MergeResult) -> None:
        g = self._f["hdr"]
        g["done"][index] = 0
        g["radiance"][index] = result.radiance
        g["variance"][index] = np.where(np.isfinite(result.variance), result.variance, np.inf).astype("f4")
        g["count"][index] = result.count
        g["saturated"][index] = result.saturated.astype("u1")
        g["saturation_level"][index] = result.saturation_level
        self._f.flush()
        g["done"][index] = 1  # the commit flag, written last
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
