"""The technician's page in a real headless browser: Debian's chromium driven by playwright,
against a real daemon process with the simulated devices.

``make test`` installs chromium (its ``browser`` target); without it these tests fail.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import httpx
import pytest
from conftest import write_config
from playwright.sync_api import expect, sync_playwright
from test_worker import captured  # noqa: F401 - a finished run of three positions

TOKEN = "t0k-for-the-page-0123"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
# Debian's chromium, not a browser downloaded by `playwright install` (no network for that).
# The flags keep it from reaching for the network it does not have.
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]


def chromium_executable() -> str:
    found = shutil.which("chromium") or next(
        (p for p in ("/usr/bin/chromium", "/usr/bin/chromium-browser") if Path(p).exists()), None
    )
    if found is None:
        pytest.fail(
            "chromium is not installed: run `make test` (its `browser` target installs Debian's "
            "chromium) or `make browser`, or `apt-get install chromium`",
            pytrace=False,
        )
    return found


@pytest.fixture()
def page(tmp_path):
    """A fresh headless chromium (own profile) and a page that records script errors."""
    executable = chromium_executable()
    with sync_playwright() as pw:
        context = pw.chromium.launch_persistent_context(
            str(tmp_path / "chromium-profile"),
            executable_path=executable,
            headless=True,
            args=CHROMIUM_ARGS,
            viewport={"width": 1366, "height": 900},
        )
        try:
            page = context.pages[0] if context.pages else context.new_page()
            page.script_errors = []
            page.on("pageerror", lambda exc: page.script_errors.append(str(exc)))
            page.set_default_timeout(15_000)
            yield page
        finally:
            context.close()


def open_page(page, daemon) -> None:
    """Open the page and type the token: it guards the reads (the presets, the runs) too."""
    page.goto(daemon.url + "/")
    expect(page.locator("#health-status")).to_have_text("ok")  # the health needs no token
    page.fill("#token", TOKEN)
    # The presets are in the select, with the daemon's default bracket in the form.
    expect(page.locator("#preset option[value=light-sweep]")).to_have_count(1)
    expect(page.locator("#exposures")).to_have_value("0.0002, 0.001, 0.005")


def test_a_run_started_from_the_page_completes_with_preview_and_download(tmp_path, daemon_factory, page):
    daemon = daemon_factory(write_config(tmp_path / "daemon.toml", tmp_path / "data"), token=TOKEN)
    open_page(page, daemon)
    expect(page.locator("#arm-connected")).to_have_text("connected")
    expect(page.locator("#arm-identity")).to_contain_text("simulated stage")
    expect(page.locator("#arm-alarm")).to_have_text("none")
    expect(page.locator("#camera-identity")).to_contain_text("SIM-0001")
    expect(page.locator("#stop-arm")).to_be_enabled()

    page.select_option("#preset", "light-sweep")
    page.fill("#exposures", "0.001, 0.005")
    page.fill("#count", "8")
    page.fill("#operator", "page test")
    page.click("#start")

    expect(page.locator("#message")).to_contain_text("started: 8 positions")
    expect(page.locator("#percent")).to_have_text("100 %", timeout=60_000)
    expect(page.locator("#state")).to_have_text("complete")
    expect(page.locator("#follow-mode")).to_have_text("live")  # followed through server-sent events
    run_id = page.locator("#run-id").inner_text()
    with daemon.client() as http:
        status = http.get(f"/runs/{run_id}").json()
    assert status["state"] == "complete" and status["n_positions"] == 8, status
    assert status["exposures_per_position"] == 2
    assert page.eval_on_selector("#progress", "e => e.value") == 100
    expect(page.locator("#positions")).to_contain_text("8 / 8")
    expect(page.locator("#last-error")).to_have_text("none")
    for finished in ("#pause", "#resume", "#abort"):
        expect(page.locator(finished)).to_be_disabled()

    # The latest frame of this run has loaded.
    preview = page.locator("#preview")
    expect(preview).to_be_visible()
    assert page.eval_on_selector("#preview", "e => e.getAttribute('src')").startswith(f"/runs/{run_id}/preview.png?t=")
    page.wait_for_function(
        "() => { const i = document.getElementById('preview'); return i.complete && i.naturalWidth > 0; }"
    )

    # The run is listed, with its download link and a process button that queues a job.
    row = page.locator(f'#runs tr[data-run-id="{run_id}"]')
    expect(row).to_contain_text("complete")
    expect(row).to_contain_text("100 %")
    link = row.locator("a.download")
    expect(link).to_have_attribute("href", status["file_url"])
    assert httpx.get(daemon.url + link.get_attribute("href"), timeout=30).status_code == 401  # the token guards it
    with page.expect_download() as clicked:  # the browser's own download carries the page's session
        link.click()
    assert Path(clicked.value.path()).read_bytes()[:8] == b"\x89HDF\r\n\x1a\n"
    row.locator("button.process").click()
    expect(page.locator("#message")).to_contain_text(f"queued for run {run_id}")
    with daemon.client() as http:
        jobs = http.get("/jobs", params={"run_id": run_id}).json()
    assert len(jobs) == 1 and jobs[0]["state"] == "queued", jobs
    expect(row.locator(".job-state")).to_contain_text("queued")

    assert page.evaluate("localStorage.getItem('mirrorgonio.token')") == TOKEN
    page.screenshot(path=str(tmp_path / "page.png"), full_page=True)

    # The controls of a longer run: pause, resume, stop the arm (pauses the run), abort.
    page.fill("#count", "")
    page.click("#start")
    expect(page.locator("#message")).to_contain_text("started: 66 positions")
    expect(page.locator("#run-id")).not_to_have_text(run_id)
    second = page.locator("#run-id").inner_text()
    expect(page.locator("#state")).to_have_text("running")
    expect(page.locator("#pause")).to_be_enabled()
    expect(page.locator("#resume")).to_be_disabled()
    expect(page.locator("#eta")).to_contain_text("ETA")
    page.click("#pause")
    expect(page.locator("#state")).to_have_text("paused")
    expect(page.locator("#pause")).to_be_disabled()
    page.click("#resume")
    expect(page.locator("#state")).to_have_text("running")
    page.click("#stop-arm")
    expect(page.locator("#message")).to_contain_text("Arm stopped")
    expect(page.locator("#state")).to_have_text("paused")  # a stopped arm pauses the run
    expect(page.locator("#last-error")).to_contain_text("arm stopped by the operator at position")
    page.click("#resume")  # a resume clears the last error
    expect(page.locator("#state")).to_have_text("running")
    expect(page.locator("#last-error")).to_have_text("none")
    page.once("dialog", lambda dialog: dialog.accept())
    page.click("#abort")
    expect(page.locator("#state")).to_have_text("aborted")
    for finished in ("#pause", "#resume", "#abort"):
        expect(page.locator(finished)).to_be_disabled()
    expect(page.locator(f'#runs tr[data-run-id="{second}"]')).to_contain_text("aborted")
    with daemon.client() as http:
        assert http.get(f"/runs/{second}").json()["state"] == "aborted"
    assert page.script_errors == []


def test_the_page_shows_what_the_daemon_refuses_and_polls_without_events(tmp_path, daemon_factory, page):
    daemon = daemon_factory(write_config(tmp_path / "daemon.toml", tmp_path / "data"), token=TOKEN)
    page.add_init_script("delete window.EventSource")  # a browser (or proxy) without server-sent events
    open_page(page, daemon)
    message = page.locator("#message")
    expect(message).to_be_hidden()

    page.fill("#count", "8")
    page.fill("#token", "")
    page.click("#start")  # no token
    expect(message).to_contain_text("a bearer token is required (HTTP 401)")

    page.fill("#token", TOKEN)
    page.fill("#exposures", "-1")
    page.click("#start")
    expect(message).to_contain_text("bracket.fixed.exposures_s.0: Input should be greater than or equal to 0.00001")
    expect(message).to_contain_text("HTTP 422")
    expect(message).to_have_class("message error")

    with daemon.client() as http:
        assert http.get("/runs").json() == []
    page.screenshot(path=str(tmp_path / "refused.png"), full_page=True)

    # Without EventSource the page follows the run by polling.
    page.fill("#exposures", "0.001")
    page.fill("#count", "3")
    page.click("#start")
    expect(message).to_contain_text("started: 3 positions")
    expect(message).to_have_class("message info")
    expect(page.locator("#percent")).to_have_text("100 %", timeout=60_000)
    expect(page.locator("#state")).to_have_text("complete")
    assert page.evaluate("typeof window.EventSource") == "undefined"
    page.wait_for_function(
        "() => { const i = document.getElementById('preview'); return i.complete && i.naturalWidth > 0; }"
    )
    assert page.script_errors == []


def test_the_page_shows_each_job_and_links_its_report_ies_and_ray_file(tmp_path, daemon_factory, page, captured):
    from test_worker import Data

    from acquisition.worker import JobWorker

    data = Data(tmp_path / "data")  # a finished run in the daemon's catalog, as a run the daemon took
    _, _, source = captured
    run = data.run(source)
    daemon = daemon_factory(write_config(tmp_path / "daemon.toml", data.root), token=TOKEN)
    open_page(page, daemon)
    expect(page.locator("#jobs")).to_contain_text("no processing jobs yet")
    row = page.locator(f'#runs tr[data-run-id="{run.id}"]')
    expect(row).to_contain_text("complete")
    row.locator("button.process").click()
    expect(page.locator("#message")).to_contain_text(f"queued for run {run.id} (steps hdr,sources)")
    with daemon.client() as http:
        job = http.get("/jobs", params={"run_id": run.id}).json()[0]
    job_row = page.locator(f'#jobs tr[data-job-id="{job["id"]}"]')
    expect(job_row.locator(".job-badge")).to_have_text("queued")
    expect(job_row).to_contain_text(run.id)

    done = JobWorker(data.catalog, worker_id="page-worker").run_once()  # the worker, beside the daemon
    assert done.state == "complete", done
    expect(job_row.locator(".job-badge")).to_have_text("complete", timeout=20_000)
    expect(job_row).to_contain_text("3 of 66 positions")
    expect(job_row.locator("progress")).to_have_attribute("value", "100")
    links = {
        kind: job_row.locator(f"a.artifact-{kind}")
        for kind in ("report", "ies", "tm25", "ldt", "light_model", "results")
    }
    for kind, link in links.items():
        expect(link).to_have_attribute("href", f"/jobs/{job['id']}/artifacts/{kind}")
    expect(links["report"]).to_have_text("report")
    expect(links["ies"]).to_have_text("IES")
    expect(links["tm25"]).to_have_text("ray file (TM-25)")
    expect(links["results"]).to_have_text("results (.zip)")  # the results file and its position files
    # The run's row links the latest job's report, IES and ray file too.
    expect(row.locator(".job-state")).to_contain_text("complete")
    assert row.locator("a.artifact").count() == 3
    for kind in ("report", "ies", "tm25"):
        answer = httpx.get(daemon.url + links[kind].get_attribute("href"), headers=AUTH, timeout=30)
        assert answer.status_code == 200 and answer.content == Path(done.artifacts[kind]).read_bytes()
    archive = httpx.get(daemon.url + links["results"].get_attribute("href"), headers=AUTH, timeout=30)
    assert archive.status_code == 200 and archive.content[:4] == b"PK\x03\x04"
    # The report opens in the browser.
    with page.context.expect_page() as opened:
        links["report"].click()
    report = opened.value
    report.wait_for_load_state()
    assert "mirrorgonio light report" in report.title()
    report.close()
    page.screenshot(path=str(tmp_path / "jobs.png"), full_page=True)
    data.catalog.close()
    assert page.script_errors == []


def test_the_next_job_takes_the_options_set_on_the_page(tmp_path, daemon_factory, page, captured):
    """The processing options on the page (the pinhole's diameter fitted or not, the intensity
    model) go with the next `process` click as the job's options, as `POST /runs/{id}/process`
    takes them; only those that differ from the worker's defaults."""
    from test_worker import Data

    data = Data(tmp_path / "data")
    run = data.run(captured[2])
    daemon = daemon_factory(write_config(tmp_path / "daemon.toml", data.root), token=TOKEN)
    open_page(page, daemon)
    row = page.locator(f'#runs tr[data-run-id="{run.id}"]')
    expect(row).to_contain_text("complete")
    expect(page.locator("#fit-aperture")).to_have_value("auto")  # the worker's default
    expect(page.locator("#fit-model")).to_have_value("gaussian")
    message = page.locator("#message")
    choices = [
        ("always", True, "polynomial", "steps hdr,sources, aperture fitted, sensor distance fitted, polynomial fits"),
        ("never", False, "gaussian", "steps hdr,sources, aperture as described"),
        ("auto", False, "gaussian", "steps hdr,sources"),
    ]
    for aperture, distance, model, said in choices:
        page.select_option("#fit-aperture", aperture)
        page.set_checked("#fit-sensor-distance", distance)
        page.select_option("#fit-model", model)
        row.locator("button.process").click()
        expect(message).to_contain_text(f"queued for run {run.id} ({said}).")
    page.screenshot(path=str(tmp_path / "options.png"), full_page=True)
    with daemon.client() as http:
        jobs = sorted(http.get("/jobs", params={"run_id": run.id}).json(), key=lambda job: job["created_utc"])
    options = [
        {"fit_aperture": "always", "fit_sensor_distance": "always", "fit": "polynomial"},
        {"fit_aperture": "never"},
        {},
    ]
    assert sorted((job["options"] for job in jobs), key=len) == sorted(options, key=len)
    for job in jobs:
        said = next(said for (*_, said), opts in zip(choices, options, strict=False) if opts == job["options"])
        expect(page.locator(f'#jobs tr[data-job-id="{job["id"]}"] td').first).to_have_attribute("title", said)
    data.catalog.close()
    assert page.script_errors == []
