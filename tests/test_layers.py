"""The package layers of the design card, checked by import-linter (pyproject.toml)."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_import_contracts_hold():
    lint = Path(sys.executable).with_name("lint-imports")
    result = subprocess.run([str(lint), "--no-cache"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
    # All three contracts were checked, and kept.
    assert "3 kept, 0 broken" in result.stdout, result.stdout


def test_import_contracts_would_catch_a_violation(tmp_path):
    """A copy of the tree with processing importing sim_devices must fail the check."""
    import shutil

    for package in ("acquisition", "processing", "drivers", "sim_devices"):
        shutil.copytree(ROOT / package, tmp_path / package, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    (tmp_path / "processing" / "leak.py").write_text("import sim_devices.optics\n")
    lint = Path(sys.executable).with_name("lint-imports")
    env = {"PYTHONPATH": str(tmp_path), "PATH": "/usr/bin:/bin"}
    result = subprocess.run([str(lint), "--no-cache"], cwd=tmp_path, capture_output=True, text=True, env=env, timeout=120)
    assert result.returncode != 0
    assert "processing never imports the simulated devices" in result.stdout
    assert "BROKEN" in result.stdout
