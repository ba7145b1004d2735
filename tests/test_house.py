"""The house rules a reader relies on, checked over the packages' source: modules and
functions of a size a reader can hold, imports at the top (the project's own always), no
private name borrowed from another module, and no date in the code or the README (history
lives in the commit messages, measured figures in docs/benchmarks.md)."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("acquisition", "processing", "drivers", "sim_devices")
MAX_MODULE_LINES = 800
MAX_FUNCTION_LINES = 80
#: A longer function says why in its docstring with these words (e.g. a numba kernel whose
#: loop must stay whole to compile to one loop).
KEPT_WHOLE = re.compile(r"\bkept whole\b", re.IGNORECASE)
#: Where the project's own modules may be imported inside a function: the command line's
#: commands import their work when they run, so that the program starts at once. Elsewhere a
#: heavy or optional part of the project (the simulated devices in the daemon, Dask's plugins)
#: is imported in a function with ruff's ``noqa: PLC0415`` and the reason on its line.
LAZY_PROJECT_IMPORTS = ("acquisition/cli/",)
SAYS_WHY = "noqa: PLC0415 - "
DATE = re.compile(r"20\d\d-[01]\d-[0-3]\d")  # as `grep "20[0-9][0-9]-[01][0-9]-[0-3][0-9]"`


def _modules(root: Path = ROOT) -> list[Path]:
    return sorted(p for package in PACKAGES for p in (root / package).rglob("*.py"))


def _name(path: Path, root: Path = ROOT) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules_too_long(root: Path = ROOT) -> list[str]:
    """Modules over :data:`MAX_MODULE_LINES` lines."""
    out = []
    for path in _modules(root):
        lines = path.read_text(encoding="utf-8").count("\n")
        if lines > MAX_MODULE_LINES:
            out.append(f"{path.relative_to(root)}: {lines} lines")
    return out


def function_lines(node: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """A function's lines, its signature and code, without its docstring (documentation is not
    what a reader has to hold)."""
    lines = node.end_lineno - node.lineno + 1
    first = node.body[0]
    if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str):
        lines -= first.end_lineno - first.lineno + 1
    return lines


def functions_too_long(root: Path = ROOT) -> list[str]:
    """Functions over :data:`MAX_FUNCTION_LINES` lines (docstring aside) whose docstring does not
    say why."""
    out = []
    for path in _modules(root):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                lines = function_lines(node)
                if lines > MAX_FUNCTION_LINES and not KEPT_WHOLE.search(ast.get_docstring(node) or ""):
                    out.append(f"{path.relative_to(root)}:{node.lineno}: {node.name}, {lines} lines")
    return out


def _imported(node: ast.Import | ast.ImportFrom, module: str, is_package: bool) -> list[tuple[str, str | None]]:
    """(module, name) pairs an import statement brings in; relative imports resolved."""
    if isinstance(node, ast.Import):
        return [(alias.name, None) for alias in node.names]
    base = node.module or ""
    if node.level:
        parent = module.split(".") if is_package else module.split(".")[:-1]
        parent = parent[: len(parent) - (node.level - 1)]
        base = ".".join([*parent, *([node.module] if node.module else [])])
    return [(base, alias.name) for alias in node.names]


def local_project_imports(root: Path = ROOT) -> list[str]:
    """Imports of the project's own modules inside functions (outside the command line)."""
    out = []
    for path in _modules(root):
        relative = str(path.relative_to(root))
        if relative.startswith(LAZY_PROJECT_IMPORTS):
            continue
        module = _name(path, root)
        text = path.read_text(encoding="utf-8")
        lines = text.splitlines()
        for function in ast.walk(ast.parse(text)):
            if not isinstance(function, ast.FunctionDef | ast.AsyncFunctionDef):
                continue
            for node in ast.walk(function):
                if isinstance(node, ast.Import | ast.ImportFrom) and SAYS_WHY not in lines[node.lineno - 1]:
                    for target, _ in _imported(node, module, path.name == "__init__.py"):
                        if target.split(".")[0] in PACKAGES:
                            out.append(f"{relative}:{node.lineno}: imports {target} in {function.name}")
    return out


def private_imports(root: Path = ROOT) -> list[str]:
    """Private names (``_x``) imported from another of the project's modules."""
    out = []
    for path in _modules(root):
        module = _name(path, root)
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom):
                for target, name in _imported(node, module, path.name == "__init__.py"):
                    private = name is not None and name.startswith("_") and not name.startswith("__")
                    if private and target.split(".")[0] in PACKAGES and target != module:
                        out.append(f"{path.relative_to(root)}:{node.lineno}: {target}.{name}")
    return out


def dates(root: Path = ROOT) -> list[str]:
    """Dates (YYYY-MM-DD) in the packages' code and in the README."""
    out = []
    for path in [*_modules(root), root / "README.md"]:
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            if DATE.search(line):
                out.append(f"{path.relative_to(root)}:{number}: {line.strip()[:80]}")
    return out


@pytest.mark.parametrize("rule", [modules_too_long, functions_too_long, local_project_imports, private_imports, dates])
def test_the_house_rules_hold(rule):
    assert rule() == []


def test_the_rules_see_what_they_forbid(tmp_path):
    """Each rule finds a planted breach of it (a rule that cannot fail checks nothing)."""
    for package in PACKAGES:
        (tmp_path / package).mkdir()
        (tmp_path / package / "__init__.py").write_text("")
    (tmp_path / "README.md").write_text("Measured on 2026-11-22.\n")
    body = "\n".join(f"    x{k} = {k}" for k in range(MAX_FUNCTION_LINES))
    long = (
        f"def long():\n    '''Too long.'''\n{body}\n\n\n"
        f"def kept():\n    '''Kept whole: a kernel.'''\n{body}\n" + "\n" * MAX_MODULE_LINES
    )
    (tmp_path / "processing" / "long.py").write_text(long)
    (tmp_path / "processing" / "lazy.py").write_text(
        "from processing.long import _hidden\n\n\ndef f():\n    from .long import kept\n    import json\n"
        "    import processing.heavy  # noqa: PLC0415 - heavy\n"
    )
    (tmp_path / "acquisition" / "cli").mkdir()
    (tmp_path / "acquisition" / "cli" / "command.py").write_text("def run():\n    import processing.long\n")
    assert modules_too_long(tmp_path) == [f"processing/long.py: {long.count(chr(10))} lines"]
    assert functions_too_long(tmp_path) == [f"processing/long.py:1: long, {MAX_FUNCTION_LINES + 1} lines"]
    assert local_project_imports(tmp_path) == ["processing/lazy.py:5: imports processing.long in f"]
    assert private_imports(tmp_path) == ["processing/lazy.py:1: processing.long._hidden"]
    assert dates(tmp_path) == ["README.md:1: Measured on 2026-11-22."]
