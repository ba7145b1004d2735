"""``mirrorgonio reflectance``: an object's albedo under three light models."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from acquisition.cli.app import RigOption, app, declared_values, default_rig, fail, with_declared_options
from drivers.contracts.rig import RigError, load_rig
from processing import ReflectanceThresholds, declared_options

if TYPE_CHECKING:
    from processing import ReflectanceResult

IgnoreCorruptOption = Annotated[
    bool,
    typer.Option(
        "--ignore-corrupt",
        help="Leave out the light positions with a frame that fails its checksum (said on stderr and in "
        "reflectance.json). Without it such a frame stops the reflectance before any work.",
    ),
]
OverwriteOption = Annotated[
    bool,
    typer.Option(
        "--overwrite",
        help="Write over outputs in --out that another run's reflectance wrote (or whose run is unknown). "
        "Without it they stop the reflectance before any work.",
    ),
]


# --- reflectance ----------------------------------------------------------------------------
def reflectance(
    object_run: Annotated[Path, typer.Argument(help="The object run (HDF5), object-arc on a rig with \\[object].")],
    light: Annotated[
        Path | None,
        typer.Option(
            "--light",
            help=(
                "Light model: RUN.light.json, or the light run's results folder or file (default: the one the "
                "run recorded)."
            ),
        ),
    ] = None,
    mesh: Annotated[
        Path | None, typer.Option("--mesh", help="The object's mesh, PLY/OBJ/STL (default: the rig's \\[object].mesh).")
    ] = None,
    out: Annotated[
        Path | None, typer.Option("--out", help="Folder for the outputs (default: RUN.reflectance beside the run).")
    ] = None,
    *,
    texture_size: Annotated[int, typer.Option(min=16, help="UV texture size in texels (meshes with UVs).")] = 1024,
    ignore_corrupt: IgnoreCorruptOption = False,
    overwrite: OverwriteOption = False,
    **thresholds: Any,
) -> None:
    """The object's diffuse albedo under three light models (collimated, isotropic point, measured),
    with maps, a UV texture, profiles along its vertical axis and an HTML report (docs/reflectance.md)."""
    from rich.progress import Progress, TaskID

    from processing import ReflectanceError, ReflectanceSettings, reflectance_from_run

    try:
        settings = ReflectanceSettings(**declared_values(THRESHOLDS, thresholds))
        with Progress(transient=True) as bar:
            tasks: dict[str, TaskID] = {}

            def progress(stage: str, done: int, total: int) -> None:
                if stage not in tasks:
                    tasks[stage] = bar.add_task(stage, total=total)
                bar.update(tasks[stage], completed=done, total=total)

            result = reflectance_from_run(
                object_run,
                light,
                mesh,
                out,
                progress=progress,
                settings=settings,
                texture_size=texture_size,
                ignore_corrupt=ignore_corrupt,
                overwrite=overwrite,
            )
    except (ReflectanceError, ValueError, OSError) as exc:  # every input error is a one-line ValueError
        raise fail(" ".join(str(exc).split())) from None
    _print_summary(result)


#: The thresholds of the sample selection, as ``processing.options`` declares them: the command's options
#: between --out and --texture-size.
THRESHOLDS = declared_options(ReflectanceThresholds)
app.command("reflectance")(with_declared_options(reflectance, THRESHOLDS, after="out"))


def _print_summary(result: ReflectanceResult) -> None:
    """The albedo per light model as a table, what was left out, the warnings (on stderr) and
    where the files are."""
    from rich.console import Console
    from rich.table import Table

    summary = result.summary()
    table = Table(
        title=f"albedo of {summary['valid']} of {summary['on_object']} superpixels on the object", title_justify="left"
    )
    for column in ("light model", "median ρ (R, G, B)", "CV", "robust CV"):
        table.add_column(column)
    for method, stats in summary["methods"].items():
        table.add_row(
            method,
            ", ".join(f"{v:.4f}" for v in stats.get("median", [])),
            f"{100 * stats.get('cv', float('nan')):.2f} %",
            f"{100 * stats.get('robust_cv', float('nan')):.2f} %",
        )
    console = Console()
    console.print(table)
    left_out = {k: v for k, v in summary["pixel_reasons"].items() if v and k not in ("valid", "background")}
    console.print("left out: " + (", ".join(f"{k} {v}" for k, v in left_out.items()) or "none"), highlight=False)
    if result.materials is not None:
        console.print(_brdf_table(result.materials.summary()))
    elif "brdf_skipped" in result.metadata:
        console.print(f"BRDF not fitted: {result.metadata['brdf_skipped']}", highlight=False)
    for warning in result.warnings:
        typer.echo(f"warning: {warning}", err=True)
    folder = result.outputs["report.html"].parent
    assets = ", brdf-*.exr, object-*.glb" if result.materials is not None else ""
    typer.echo(
        f"outputs in {folder}: report.html, reflectance.json, reflectance.h5, albedo-*.exr/png, profiles.png{assets}"
    )


def _brdf_table(summary: dict[str, Any]) -> Any:
    """Per light model: points with their own lobe and shared ones, the medians, the relighting error."""
    from rich.table import Table

    held = summary["held_out_positions"]
    table = Table(title=f"BRDF per point (relit: {len(held)} held-out positions)", title_justify="left")
    for column in (
        "light model",
        "own lobe",
        "shared",
        "median ρ (R, G, B)",
        "median F0 (R, G, B)",
        "median α",
        "relit RMS",
    ):
        table.add_column(column)
    for method, stats in summary["methods"].items():
        relit = stats.get("relighting", {}).get("rms_relative")
        table.add_row(
            method,
            str(stats["confidence"]["own"]),
            str(stats["confidence"]["shared"]),
            ", ".join(f"{v:.4f}" for v in stats.get("diffuse_median", [])),
            ", ".join(f"{v:.4f}" for v in stats.get("specular_median", [])),
            f"{stats['roughness_median']:.3f}" if "roughness_median" in stats else "—",
            f"{100 * relit:.2f} %" if relit is not None else "—",
        )
    return table


# --- coverage ------------------------------------------------------------------------------------
def coverage(
    rig: RigOption = None,
    roughness: Annotated[
        list[float] | None,
        typer.Option(
            "--roughness",
            min=0.02,
            max=1.0,
            help="GGX roughness α to plan for; repeat for several (default: 0.15 and 0.35, a gloss and a satin).",
        ),
    ] = None,
    lobe_fraction: Annotated[
        float,
        typer.Option(min=0.01, max=1.0, help="A sample counts where the lobe is at least this share of its peak."),
    ] = 0.25,
    out: Annotated[
        Path | None, typer.Option("--out", help="Folder for coverage.json and the maps (default: none written).")
    ] = None,
) -> None:
    """Before an object run: which points of the object the rig's schedule shows a highlight on,
    counted per point the camera sees and per texel of the mesh's UV layout (docs/reflectance.md)."""
    from rich.console import Console
    from rich.table import Table

    from processing import ReflectanceError, highlight_coverage, write_coverage

    try:
        loaded = load_rig(rig or default_rig())
        plans = [
            highlight_coverage(loaded, roughness=alpha, lobe_fraction=lobe_fraction)
            for alpha in (roughness or [0.15, 0.35])
        ]
        written = write_coverage(plans, out) if out is not None else []
    except (ReflectanceError, RigError, ValueError, OSError) as exc:
        raise fail(" ".join(str(exc).split())) from None
    table = Table(
        title=f"highlight samples of {plans[0].positions} light positions ({loaded.schedule.kind})",
        title_justify="left",
    )
    for column in ("roughness α", "points seen", "≥ 1 highlight", "≥ 3 highlights", "median"):
        table.add_column(column)
    for plan in plans:
        s = plan.summary()
        table.add_row(
            f"{plan.roughness:g}",
            str(s["points"]),
            f"{100 * s['share_with_highlight']:.1f} %",
            f"{100 * s['share_with_three']:.1f} %",
            f"{s['median_highlights']:g}",
        )
    Console().print(table)
    if written:
        typer.echo(f"written: {', '.join(p.name for p in written)} in {written[0].parent}")


app.command("coverage")(coverage)
