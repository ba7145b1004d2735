"""The package layers of the design card, checked by import-linter (pyproject.toml), and the
packages' third-party imports, each declared in pyproject.toml."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("acquisition", "processing", "drivers", "sim_devices")


def _contract_names() -> list[str]:
    import tomllib

    config = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["importlinter"]
    return [contract["name"] for contract in config["contracts"]]


def _lint_imports(root: Path, env: dict | None = None) -> subprocess.CompletedProcess:
    lint = Path(sys.executable).with_name("lint-imports")
    return subprocess.run([str(lint), "--no-cache"], cwd=root, capture_output=True, text=True, env=env, timeout=120)


def test_import_contracts_hold():
    result = _lint_imports(ROOT)
    assert result.returncode == 0, result.stdout + result.stderr
    # Every contract of pyproject.toml was checked, and kept.
    assert f"{len(_contract_names())} kept, 0 broken" in result.stdout, result.stdout


def test_the_layers_name_every_root_package():
    """The layers contract is exhaustive at the top: every root package stands in one layer."""
    import tomllib

    config = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["importlinter"]
    (layers,) = [c["layers"] for c in config["contracts"] if c["type"] == "layers" and "containers" not in c]
    named = {name.strip() for layer in layers for name in layer.split("|")}
    assert named == set(config["root_packages"]) == set(PACKAGES)


def _planted(tmp_path: Path, module: str, source: str) -> subprocess.CompletedProcess:
    """lint-imports on a copy of the tree with ``module`` added, holding ``source``."""
    import shutil

    for package in PACKAGES:
        shutil.copytree(ROOT / package, tmp_path / package, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    (tmp_path / module).write_text(source)
    return _lint_imports(tmp_path, {"PYTHONPATH": str(tmp_path), "PATH": "/usr/bin:/bin"})


def test_import_contracts_would_catch_a_violation(tmp_path):
    """A copy of the tree with processing importing sim_devices must fail the check."""
    result = _planted(tmp_path, "processing/leak.py", "import sim_devices.optics\n")
    assert result.returncode != 0
    assert "processing never imports the simulated devices" in result.stdout
    assert "BROKEN" in result.stdout


def test_an_import_cycle_breaks_the_acyclic_contract(tmp_path):
    """The report importing the light run, which imports the report: a cycle between siblings."""
    result = _planted(tmp_path, "processing/report/leak.py", "import processing.light_run.run\n")
    assert result.returncode != 0
    broken = result.stdout[result.stdout.index("Broken contracts") :]
    assert "no import cycles between sibling modules or packages" in broken, result.stdout
    assert "No cycles are allowed in processing." in broken, result.stdout


def test_an_upward_import_breaks_the_layers(tmp_path):
    """The ground floor importing the processing (an upward import) fails the layers contract."""
    result = _planted(tmp_path, "drivers/contracts/leak.py", "import processing.trace\n")
    assert result.returncode != 0
    broken = result.stdout[result.stdout.index("Broken contracts") :]
    assert "layers: acquisition above processing" in broken, result.stdout
    assert "drivers.contracts.leak -> processing.trace" in broken, result.stdout


def _front_door_contract() -> dict:
    import tomllib

    config = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["importlinter"]
    (contract,) = [c for c in config["contracts"] if "front door" in c["name"]]
    return contract


def test_the_front_door_contract_names_every_module_behind_it():
    """Every sub-package and module of ``processing`` is behind the door: one added later
    cannot be reached from the daemon or the command line by being left off the list."""
    behind = {
        f"processing.{path.stem if path.is_file() else path.name}"
        for path in (ROOT / "processing").iterdir()
        if (path.suffix == ".py" and path.stem != "__init__") or (path / "__init__.py").is_file()
    }
    contract = _front_door_contract()
    assert set(contract["forbidden_modules"]) == behind
    assert {"acquisition.daemon", "acquisition.cli"} <= set(contract["source_modules"])


def test_a_reach_behind_the_front_door_breaks_its_contract(tmp_path):
    """The worker's package importing a processing module directly fails the front door's contract."""
    result = _planted(tmp_path, "acquisition/daemon/leak.py", "from processing.light_run.run import process_run\n")
    assert result.returncode != 0
    broken = result.stdout[result.stdout.index("Broken contracts") :]
    assert _front_door_contract()["name"] in " ".join(broken.split()), result.stdout
    assert "acquisition.daemon.leak -> processing.light_run.run" in broken, result.stdout


# --- declared dependencies ---------------------------------------------------------------------


def _imported_top_level_modules(folder: Path, root: Path) -> dict[str, str]:
    """Every absolute import's top-level module under ``folder``: the first file importing it."""
    import ast

    found: dict[str, str] = {}
    for path in sorted(folder.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                found.setdefault(name.split(".")[0], str(path.relative_to(root)))
    return found


def _requirement_names(requirements: list[str]) -> set[str]:
    """The distributions ``requirements`` name, and those their extras bring in (``dask[distributed]``
    declares ``distributed``), as far as the installed metadata says."""
    from importlib.metadata import PackageNotFoundError, requires

    from packaging.requirements import Requirement
    from packaging.utils import canonicalize_name

    names = set()
    for text in requirements:
        requirement = Requirement(text)
        names.add(canonicalize_name(requirement.name))
        try:
            brought = requires(requirement.name) or []
        except PackageNotFoundError:
            continue
        for extra in requirement.extras:
            for line in map(Requirement, brought):
                if line.marker is not None and line.marker.evaluate({"extra": extra}):
                    names.add(canonicalize_name(line.name))
    return names


def undeclared_imports(root: Path = ROOT) -> list[str]:
    """Third-party modules the packages import whose distribution pyproject.toml does not name:
    in the main dependencies, or in a feature's optional extra (``bench``, ``gphoto2``: modules
    imported only where that feature is asked for). The ``test`` extra does not count: the
    packages run without it. One line each, naming the file."""
    import tomllib
    from importlib.metadata import packages_distributions

    from packaging.utils import canonicalize_name

    project = tomllib.loads((root / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    declared = _requirement_names(project["dependencies"])
    for extra, requirements in project.get("optional-dependencies", {}).items():
        if extra != "test":
            declared |= _requirement_names(requirements)
    distributions = packages_distributions()
    problems = []
    for package in PACKAGES:
        for module, where in sorted(_imported_top_level_modules(root / package, root).items()):
            if module in sys.stdlib_module_names or module in PACKAGES or module == "__future__":
                continue
            # An extension module at the top level (OpenEXR) or one not installed here (gphoto2) is
            # not in Python 3.11's map: its own name is then taken as the distribution's.
            names = {canonicalize_name(d) for d in distributions.get(module, [module])}
            if not names & declared:
                problems.append(
                    f"{where}: imports {module} ({', '.join(sorted(names))}), "
                    "which pyproject.toml does not declare "
                    "(the test extra does not count)"
                )
    return problems


def test_every_third_party_import_is_a_declared_dependency():
    assert undeclared_imports() == []


def test_an_undeclared_import_is_named_with_its_file(tmp_path):
    for package in PACKAGES:
        (tmp_path / package).mkdir()
        (tmp_path / package / "__init__.py").write_text("")
    (tmp_path / "acquisition" / "client.py").write_text("def get():\n    import httpx\n    import numpy.linalg\n")
    # httpx is declared, but only for the tests: a package that imports it needs it at run time.
    (tmp_path / "pyproject.toml").write_text(
        '[project]\nname = "x"\ndependencies = ["numpy>=1.26"]\n[project.optional-dependencies]\ntest = ["httpx"]\n'
    )
    assert undeclared_imports(tmp_path) == [
        "acquisition/client.py: imports httpx (httpx), which pyproject.toml does not declare (the test extra does "
        "not count)"
    ]
