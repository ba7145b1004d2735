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
#: What points outside the repository: a path up out of it to a shared folder, an absolute
#: path of a machine's work folder, a design note by a bare name (the repository's own page
#: is ``docs/measurement.md``, linked from docs/ as ``measurement.md``).
OUTSIDE = re.compile(r"\.\./+shared\b|/wor[k]/|\bshared/design\b")
BARE_NOTE = re.compile(r"(?<![\w/.-])measurement[.]md")
#: The text files the outside-reference rule reads (by suffix, or by whole name).
TEXT_SUFFIXES = {".py", ".md", ".toml", ".txt", ".cfg", ".cff", ".yml", ".yaml", ".json", ".html", ".js", ".css"}
TEXT_NAMES = {"Makefile", "Dockerfile"}
#: A markdown link's target: ``[text](target)`` or ``![alt](target "title")``.
MD_LINK = re.compile(r"\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")


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


def _text_files(root: Path) -> list[Path]:
    """The repository's text files: every folder but hidden ones, caches and local outputs."""
    skip = {"__pycache__", "node_modules", "build", "demo-data", "demo-output"}
    out = []
    for path in sorted(root.rglob("*")):
        parts = path.relative_to(root).parts
        if any(p.startswith(".") or p in skip or p.endswith(".egg-info") for p in parts[:-1]):
            continue
        if path.is_file() and (path.suffix in TEXT_SUFFIXES or path.name in TEXT_NAMES):
            out.append(path)
    return out


def outside_references(root: Path = ROOT) -> list[str]:
    """Lines that send the reader outside the repository (:data:`OUTSIDE`), or to a design
    note by its bare name (:data:`BARE_NOTE`) outside docs/, where ``measurement.md`` is the
    page beside the reader (its links are :func:`broken_doc_links`' to check). This file,
    which states the rule and plants breaches of it, is not read."""
    out = []
    for path in _text_files(root):
        if path == Path(__file__).resolve():
            continue
        in_docs = path.parent == root / "docs" and path.suffix == ".md"
        for number, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
            if OUTSIDE.search(line) or (not in_docs and BARE_NOTE.search(line)):
                out.append(f"{path.relative_to(root)}:{number}: {line.strip()[:80]}")
    return out


def _anchors(page: Path) -> set[str]:
    """The anchors of a markdown page's headings, as GitHub makes them: lower case, spaces
    as hyphens, punctuation but hyphens and underscores dropped."""
    anchors = set()
    for line in page.read_text(encoding="utf-8").splitlines():
        if line.startswith("#"):
            title = line.lstrip("#").strip().lower()
            anchors.add(re.sub(r"[^\w\- ]", "", title).replace(" ", "-"))
    return anchors


def broken_doc_links(root: Path = ROOT) -> list[str]:
    """Relative links of README.md and docs/*.md that do not resolve to a file (and, for a
    markdown page, a heading) inside the repository."""
    out = []
    for page in [root / "README.md", *sorted((root / "docs").glob("*.md"))]:
        for number, line in enumerate(page.read_text(encoding="utf-8").splitlines(), 1):
            for target in MD_LINK.findall(line):
                if re.match(r"[a-z][a-z0-9+.-]*:", target, re.IGNORECASE):  # http:, mailto:, ...
                    continue
                name, _, anchor = target.partition("#")
                dest = (page.parent / name).resolve() if name else page
                inside = dest == root or root in dest.parents
                no_heading = anchor and dest.suffix == ".md" and dest.is_file() and anchor not in _anchors(dest)
                if not inside or not dest.is_file() or no_heading:
                    out.append(f"{page.relative_to(root)}:{number}: {target}")
    return out


@pytest.mark.parametrize(
    "rule",
    [
        modules_too_long,
        functions_too_long,
        local_project_imports,
        private_imports,
        dates,
        outside_references,
        broken_doc_links,
    ],
)
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


def test_the_reference_rules_see_what_they_forbid(tmp_path):
    """A path out of the repository, a bare design note and a link to nowhere are found;
    the repository's own page, by its path or linked beside it, is not."""
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "measurement.md").write_text("# The measurement\n\n## The rig and its frames\n")
    (tmp_path / "docs" / "rig.md").write_text(
        "See [the page](measurement.md#the-rig-and-its-frames) and [there](measurement.md#no-such-heading).\n"
    )
    (tmp_path / "README.md").write_text("[ok](docs/rig.md), [gone](docs/gone.md), [up](../shared/note.md)\n")
    (tmp_path / "processing").mkdir()
    (tmp_path / "processing" / "fit.py").write_text(
        '"""From docs/measurement.md, step 5."""\n# the physics of measurement.md\n# see ../shared/design\n'
    )
    assert outside_references(tmp_path) == [
        "README.md:1: [ok](docs/rig.md), [gone](docs/gone.md), [up](../shared/note.md)",
        "processing/fit.py:2: # the physics of measurement.md",
        "processing/fit.py:3: # see ../shared/design",
    ]
    assert broken_doc_links(tmp_path) == [
        "README.md:1: docs/gone.md",
        "README.md:1: ../shared/note.md",
        "docs/rig.md:1: measurement.md#no-such-heading",
    ]
