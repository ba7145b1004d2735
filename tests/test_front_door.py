"""The processing's front door (``processing.__all__``): every name it lists loads, is the
object of the module behind it, and the light ones load without the processing's weight."""

import subprocess
import sys

import processing


def test_every_name_of_the_front_door_loads():
    for name in processing.__all__:
        assert getattr(processing, name) is not None, name
    assert sorted(processing.__all__) == processing.__all__, "kept sorted, so that a reader finds a name"


def test_a_name_is_the_object_behind_the_door():
    from processing.light_run.progress import describe
    from processing.light_run.run import process_run

    assert processing.process_run is process_run
    assert processing.describe_progress is describe


def test_a_name_not_in_the_front_door_is_an_attribute_error():
    try:
        processing.trace_pixels  # noqa: B018 - the look-up is the test
    except AttributeError as exc:
        assert "trace_pixels" in str(exc)
    else:
        raise AssertionError("processing.trace_pixels should not be served by the front door")


def test_the_options_load_without_the_processing():
    """The command line checks its options, and the daemon a job request, with the processing
    left unloaded: no NumPy, no Dask, no module of the light run."""
    code = (
        "import sys\n"
        "from processing import FitMethod, ProcessingOptions, OptionsError\n"
        "ProcessingOptions.checked(fit_method='gaussian')\n"
        "heavy = [m for m in sys.modules if m.split('.')[0] in ('numpy', 'dask', 'h5py', 'matplotlib')"
        " or m.startswith('processing.light_run')]\n"
        "print(heavy)\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "[]", result.stdout
