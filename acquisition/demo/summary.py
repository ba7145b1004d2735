"""What the demo made and measured: :class:`DemoResult` (also ``summary.json`` in its folder),
and the summary the command prints from it."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path

from rich.console import Console
from rich.table import Table

from acquisition.demo.folder import shown
from acquisition.demo.truth import SourceAccuracy


@dataclass
class DemoResult:
    """What the demo made and measured (also written as ``summary.json`` in its folder)."""

    data_dir: Path
    rig: Path
    run_id: str
    job_id: str
    positions: int
    frame: str
    run_file: Path
    artifacts: dict[str, Path]
    accuracy: list[SourceAccuracy]
    max_rms_rel_error: float
    target: float | None
    acquire_s: float
    process_s: float
    total_s: float
    job_message: str = ""
    layout: str = ""
    #: The camera's aperture the sources were estimated with (the light model's provenance).
    aperture: str = ""
    pids: dict[str, int] = field(default_factory=dict)

    def to_json(self) -> dict:
        """The result as JSON-ready data (paths as strings): ``summary.json``."""
        data = asdict(self)
        data["data_dir"], data["rig"], data["run_file"] = str(self.data_dir), str(self.rig), str(self.run_file)
        data["artifacts"] = {kind: str(path) for kind, path in self.artifacts.items()}
        return data


ARTIFACT_LABELS = (
    ("report", "report (HTML)"),
    ("ies", "IES"),
    ("ldt", "EULUMDAT (LDT)"),
    ("tm25", "TM-25 ray file"),
    ("light_model", "light model (JSON)"),
    ("results", "HDR results"),
)


def print_summary(result: DemoResult, console: Console) -> None:
    """Print what the demo made and measured: its files, the accuracy of each source, the times.

    Parameters
    ----------
    result : DemoResult
        What :func:`acquisition.demo.run.run_demo` returned.
    console : rich.console.Console
        Where to print.
    """
    folder = result.run_file.parent
    console.print(f"\ndemo run {result.run_id}: {result.positions} positions, {result.frame} frames", highlight=False)
    console.print(f"files in {shown(folder)}/", highlight=False, soft_wrap=True)

    def where(path: Path) -> str:
        return path.name if path.parent == folder else shown(path)

    files = Table(show_header=True)
    files.add_column("what", no_wrap=True)
    files.add_column("file", overflow="fold")
    files.add_row("run file", where(result.run_file))
    for kind, label in ARTIFACT_LABELS:
        if kind in result.artifacts:
            files.add_row(label, where(result.artifacts[kind]))
    files.add_row("logs, settings", shown(result.data_dir) + "/")
    files.add_row("source layout", result.layout)
    if result.aperture:
        files.add_row("camera aperture", result.aperture)
    console.print(files)

    target = result.target
    acc = Table(title="accuracy against the simulated truth", title_justify="left")
    acc.add_column("source", no_wrap=True)
    acc.add_column("error", justify="right", no_wrap=True)
    acc.add_column("θ covered", justify="right", no_wrap=True)
    acc.add_column("samples", justify="right", no_wrap=True)
    found = result.layout.startswith("found")
    if found:
        acc.add_column("found at", justify="right", no_wrap=True)  # the source's distance from the truth's
    for s in result.accuracy:
        cells = [
            s.name,
            f"{100 * s.rms_rel_error:.3f} %",
            f"{s.theta_min_deg:.1f}–{s.theta_max_deg:.1f}°",
            str(s.samples),
        ]
        acc.add_row(*cells, *([f"{1e6 * s.offset_m:.0f} µm off"] if found else []))
    verdict = ""
    if target is not None:
        ok = result.max_rms_rel_error <= target
        verdict = f" ({'within' if ok else '[red]above[/red]'} the {100 * target:g} % target)"
    acc.add_row(
        "[bold]max[/bold]",
        f"[bold]{100 * result.max_rms_rel_error:.3f} %[/bold]",
        "",
        "",
        *([""] if found else []),
        end_section=True,
    )
    console.print(acc)
    console.print(
        f"error = RMS(I_fit − I_true) / max(I_true) over the θ each source's samples cover; "
        f"max {100 * result.max_rms_rel_error:.3f} % of peak{verdict}",
        highlight=False,
    )

    times = Table(title="times", title_justify="left", show_header=False)
    times.add_column("step", no_wrap=True)
    times.add_column("seconds", justify="right", no_wrap=True)
    times.add_row("acquisition (REST run, simulated arm and camera)", f"{result.acquire_s:.1f} s")
    times.add_row("processing (worker job, Dask)", f"{result.process_s:.1f} s")
    times.add_row("whole demo", f"{result.total_s:.1f} s")
    console.print(times)
    if result.job_message:
        console.print(f"worker: {result.job_message}", highlight=False)
