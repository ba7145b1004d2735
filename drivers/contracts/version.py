"""The software's version, as installed (recorded in the run, results and light-model files)."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("mirrorgonio")
except PackageNotFoundError:  # a source tree that was not installed
    __version__ = "0+unknown"
