"""The daemon's commands: ``serve`` (the acquisition daemon) and ``worker`` (the processing jobs)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from acquisition.cli.app import (
    SchedulerOption,
    WorkersOption,
    app,
    domain_errors,
    fail,
)

if TYPE_CHECKING:
    from acquisition.daemon.catalog import JobRecord


# --- serve ----------------------------------------------------------------------------------
@app.command("serve")
def serve(
    config: Annotated[
        Path | None, typer.Option("--config", help="daemon.toml (docs/daemon.md); simulated rig without one.")
    ] = None,
    host: Annotated[
        str | None, typer.Option(help="Address to listen on (default from the configuration: 127.0.0.1).")
    ] = None,
    port: Annotated[int | None, typer.Option(help="TCP port (default from the configuration: 8000).")] = None,
    data_dir: Annotated[Path | None, typer.Option("--data-dir", help="Where run files and the catalog live.")] = None,
) -> None:
    """Run the acquisition daemon (REST API and web page) under uvicorn."""
    from acquisition.daemon.settings import SettingsError, load_settings

    try:
        settings = load_settings(config, host=host, port=port, data_dir=data_dir)
        settings.require_token_off_loopback()
    except (SettingsError, OSError) as exc:
        raise fail(str(exc)) from None
    from acquisition.daemon.devices import check_configured_files
    from drivers.modbus_profile import ProfileError

    try:
        check_configured_files(settings)
    except domain_errors(SettingsError, ProfileError) as exc:
        raise fail(str(exc)) from None
    import uvicorn

    from acquisition.daemon.app import create_app

    # The daemon's own lines (a run's start and end, why a client's file was refused) on stderr
    # beside uvicorn's; the page's log panel keeps its own copy.
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    try:
        uvicorn.run(create_app(settings), host=settings.host, port=settings.port, log_level="info")
    except domain_errors() as exc:
        raise fail(str(exc)) from None


# --- worker -------------------------------------------------------------------------------
WorkerConfigOption = Annotated[
    Path | None,
    typer.Option(
        "--config",
        help="daemon.toml: the worker uses its data_dir, catalog and token (MG_CATALOG, MG_TOKEN).",
    ),
]
WorkerDataOption = Annotated[
    Path | None,
    typer.Option(
        "--data-dir",
        help="Where the catalog and the run files are (overrides the configuration); with a catalog on a "
        "server, where the run files fetched from other machines' daemons are kept while processed.",
    ),
]
CatalogOption = Annotated[
    str | None,
    typer.Option(
        "--catalog",
        help="The catalog's URL (postgresql://USER@HOST/DATABASE for a lab's); default the configuration's.",
    ),
]
RigsOption = Annotated[
    list[str] | None,
    typer.Option("--rig", help="Take only this rig's jobs (repeat for several); default every rig's."),
]


@app.command("worker")
def worker_command(
    config: WorkerConfigOption = None,
    data_dir: WorkerDataOption = None,
    catalog: CatalogOption = None,
    rigs: RigsOption = None,
    scheduler: SchedulerOption = "local",
    workers: WorkersOption = None,
    once: Annotated[bool, typer.Option("--once", help="Process the jobs that can run now, then exit.")] = False,
    poll: Annotated[float, typer.Option(min=0.05, help="Seconds between looks at the queue when it is empty.")] = 2.0,
    heartbeat: Annotated[float, typer.Option(min=0.05, help="Seconds between heartbeats while a job runs.")] = 5.0,
    stale_after: Annotated[
        float,
        typer.Option(
            "--stale-after",
            min=0.1,
            help="A running job without a heartbeat for this long is requeued (its worker died).",
        ),
    ] = 60.0,
    wait: Annotated[
        float,
        typer.Option(min=0.0, help="Seconds a job whose run is still being acquired waits before it is tried again."),
    ] = 10.0,
    worker_id: Annotated[
        str | None, typer.Option("--id", help="This worker's name in the catalog (default HOST-PID).")
    ] = None,
) -> None:
    """Take queued processing jobs from the catalog and process their runs (results beside each run).

    Positions are processed on Dask: a local cluster sized to the machine, or the cluster
    of --scheduler tcp://HOST:8786. A job whose run is still being acquired waits (or, when
    it asked for partial, gets the positions complete so far); a failed job records its
    reason and the worker goes on; a job whose worker died is requeued by the next worker
    that looks at the queue. Stops on Ctrl-C or SIGTERM, after the job at hand.
    """
    import signal
    import threading

    from acquisition.daemon.settings import SettingsError, load_settings
    from acquisition.daemon.worker import serve_jobs
    from processing import ComputeError, open_compute

    try:
        settings = load_settings(config, data_dir=data_dir, catalog=catalog)
    except (SettingsError, OSError) as exc:
        raise fail(str(exc)) from None
    if not settings.shared_catalog and not Path(settings.data_dir).is_dir():
        raise fail(f"--data-dir: {settings.data_dir} is not a folder (the daemon's data folder, with catalog.sqlite)")
    if settings.shared_catalog:
        Path(settings.data_dir).mkdir(parents=True, exist_ok=True)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    from processing import warm_up_worker

    try:
        compute = open_compute(scheduler, workers=workers, warm_up=warm_up_worker)
    except ComputeError as exc:
        raise fail(str(exc)) from None
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    from acquisition.daemon.catalog import CatalogError
    from acquisition.daemon.catalog.backends import redact_url

    typer.echo(f"worker: jobs from {redact_url(settings.catalog_url)}, positions on {compute.description}")

    try:
        with compute:
            serve_jobs(
                settings.catalog_url,
                compute,
                fetch_to=Path(settings.data_dir) / "fetched",
                token=settings.token.get_secret_value() if settings.token else None,
                rigs=rigs or None,
                stop=stop,
                once=once,
                poll_s=poll,
                on_job=_say_job,
                worker_id=worker_id,
                heartbeat_s=heartbeat,
                stale_after_s=stale_after,
                wait_s=wait,
            )
    except CatalogError as exc:
        raise fail(str(exc)) from None


def _say_job(job: JobRecord) -> None:
    """One job the worker ended: its state, and what it wrote."""
    if job.state == "complete":
        typer.echo(f"{job.id} complete ({job.run_id}): {job.message}")
        for kind, path in job.artifacts.items():
            typer.echo(f"  {kind}: {path}")
    elif job.state == "failed":
        typer.echo(f"{job.id} failed ({job.run_id}): {job.error}")
    else:
        typer.echo(f"{job.id} {job.state} ({job.run_id}): {job.message}")
