"""The technician's page in a real headless browser: Debian's chromium driven by playwright,
against a real daemon process with the simulated devices.

``make test`` installs chromium (its ``browser`` target); without it these tests fail.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import httpx
import numpy as np
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


def align_from_the_page(page, daemon) -> None:
    """The alignment view of a test shot (zoom, the ball's outline, saturation, the histogram,
    the exposure), jog and home within the soft limits, the token refusing them, the log."""
    message = page.locator("#message")
    expect(page.locator("#frame-caption")).to_contain_text("no frame yet")
    page.fill("#shot-exposures", "0.001, 0.1")
    page.click("#test-shot")
    expect(message).to_contain_text("Test shot: 2 frames; the preview shows the last (1/10 s (0.1 s))")
    expect(page.locator("#shot-frames tr")).to_have_count(3)
    expect(page.locator("#shot-frames tr").nth(2).locator("td.bad")).to_have_count(1)  # saturated at 0.1 s
    expect(page.locator("#frame-caption")).to_contain_text("test shot, 500 × 328, exposure 1/10 s (0.1 s)")
    expect(page.locator("#frame-exposure")).to_have_text("1/10 s (0.1 s)")
    expect(page.locator("#frame-saturated")).to_contain_text("photosites")
    with daemon.client() as http:
        summary = http.get("/preview/frame").json()
        assert http.get("/runs").json() == []  # a test shot is no run
    assert page.locator("#frame-saturated").inner_text().startswith(f"{summary['saturated_pixels']} photosites")

    # The outline is drawn where the rig puts the ball: the cyan pixels of the canvas span it
    # (the middle and the size of their extent), and none are left once it is hidden.
    cyan = (
        "() => { const c = document.getElementById('viewer'), d = c.getContext('2d')"
        ".getImageData(0, 0, c.width, c.height).data; const xs = [], ys = [];"
        " for (let i = 0; i < d.length; i += 4) if (d[i] < 90 && d[i + 1] > 150 && d[i + 2] > 200)"
        " { xs.push((i / 4) % c.width); ys.push(Math.floor(i / 4 / c.width)); }"
        " if (!xs.length) return [0];"
        " const ext = (a) => [Math.min(...a) + 0.5, Math.max(...a) + 0.5];"
        " return [xs.length, ...ext(xs), ...ext(ys), view.ox, view.oy, view.scale]; }"
    )
    count, x0, x1, y0, y1, ox, oy, scale = page.evaluate(cyan)
    outline = np.array(summary["ball_outline_px"]) + 0.5  # pixel centres on the canvas
    assert count > 300
    for low, high, values, origin in ((x0, x1, outline[:, 0], ox), (y0, y1, outline[:, 1], oy)):
        middle = ((low + high) / 2 - origin) / scale
        assert middle == pytest.approx((values.min() + values.max()) / 2, abs=1.0)
        assert (high - low) / scale == pytest.approx(np.ptp(values), abs=3.0)  # the line's width
    page.uncheck("#show-outline")
    assert page.evaluate(cyan)[0] == 0
    page.check("#show-outline")
    fitted = page.evaluate("view.scale")
    box = page.locator("#viewer").bounding_box()
    page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    page.mouse.wheel(0, -100)
    assert page.evaluate("view.scale") == pytest.approx(1.25 * fitted)
    page.click("#zoom-1")
    expect(page.locator("#zoom-level")).to_have_text("zoom 1.0×")
    drawn = (
        "() => { const h = document.getElementById('histogram'), d = h.getContext('2d')"
        ".getImageData(0, 0, h.width, h.height).data; let n = 0;"
        " for (let i = 0; i < d.length; i += 4) if (d[i] > 150 && d[i + 1] < 90 && d[i + 2] < 90) n++; return n; }"
    )
    assert page.evaluate(drawn) > 20  # the red channel's line

    # Jog within the soft limits; beyond them, without the token, or during a run: refused.
    page.click("#jog button[data-axis=z][data-sign='-1']")
    expect(message).to_contain_text("jog z -1 mm: the arm is at")
    expect(message).to_contain_text(re.compile(r" z (198\.9\d|199\.0\d) mm"))  # read back
    page.fill("#jog-mm", "100")
    for z in (299, 399):
        page.click("#jog button[data-axis=z][data-sign='1']")
        expect(message).to_contain_text(re.compile(rf"jog z \+100 mm: .* z ({z - 1}\.9\d|{z}\.0\d) mm"))
    page.click("#jog button[data-axis=z][data-sign='1']")
    # The target is the read-back pose (its encoder noise in the last digits) plus the jog.
    expect(message).to_contain_text(re.compile(r"Jog z refused: jog z \+100 mm: z=0\.49(9\d*|8\d+) m outside"))
    expect(message).to_contain_text(
        "outside the soft limits [0.000000, 0.450000] m (the rig's arm.soft_limits) (HTTP 422)"
    )
    page.fill("#token", "")
    # The page reads its presets again without the token and says they need one; only then the
    # click, whose refusal would otherwise race that message for the one message box.
    expect(message).to_contain_text("Cannot read the presets — a bearer token is required (HTTP 401)")
    page.click("#home")
    expect(message).to_contain_text("Home refused: a bearer token is required (HTTP 401)")
    page.fill("#token", TOKEN)
    page.click("#home")
    expect(message).to_contain_text(re.compile(r"homed: the arm is at .* z (199\.9\d|200\.0\d) mm"))
    expect(page.locator("#log")).to_contain_text("jog z -1 mm: at x")
    expect(page.locator("#log")).to_contain_text("homed: at x")


def test_a_run_started_from_the_page_completes_with_the_alignment_view_and_download(tmp_path, daemon_factory, page):
    daemon = daemon_factory(write_config(tmp_path / "daemon.toml", tmp_path / "data"), token=TOKEN)
    open_page(page, daemon)
    expect(page.locator("#arm-connected")).to_have_text("connected")
    expect(page.locator("#arm-identity")).to_contain_text("simulated stage")
    expect(page.locator("#arm-alarm")).to_have_text("none")
    expect(page.locator("#camera-identity")).to_contain_text("SIM-0001")
    expect(page.locator("#stop-arm")).to_be_enabled()
    align_from_the_page(page, daemon)

    page.select_option("#preset", "light-sweep")
    page.fill("#exposures", "0.001, 0.005")
    page.fill("#count", "8")
    # The preset says what was asked: 8 positions, not the schedule's 66.
    expect(page.locator("#preset-info")).to_have_text("light-sweep: 8 of its 66 positions")
    expect(page.locator("#preset option[value=light-sweep]")).to_have_text("light-sweep (8 of its 66 positions)")
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
    expect(page.locator("#positions")).to_contain_text("8 of 8 positions")
    expect(page.locator("#current")).to_have_text("position 8 of 8")  # counted from 1, as the done count
    expect(page.locator("#last-error")).to_have_text("none")
    for finished in ("#pause", "#resume", "#abort"):
        expect(page.locator(finished)).to_be_disabled()

    # The latest frame of this run is in the alignment view.
    expect(page.locator("#frame-caption")).to_contain_text(f"run {run_id}, 500 × 328, exposure 1/200 s")

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
    expect(page.locator("#current")).to_contain_text(re.compile(r"^position \d+ of 66$"))  # counted from 1
    expect(page.locator("#step")).to_contain_text(re.compile(r"sweep, position \d+ of 66"))
    for refused in ("#test-shot", "#jog button[data-axis=x][data-sign='1']"):  # not during a run
        page.click(refused)
        expect(page.locator("#message")).to_contain_text(f"run {second} is already active on this rig (HTTP 409)")
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
    queued = queue_from_the_page(page, second)
    page.once("dialog", lambda dialog: dialog.accept())
    page.click("#abort")
    expect(page.locator("#state")).to_have_text("aborted")
    for finished in ("#pause", "#resume", "#abort"):
        expect(page.locator(finished)).to_be_disabled()
    expect(page.locator(f'#runs tr[data-run-id="{second}"]')).to_contain_text("aborted")
    with daemon.client() as http:
        assert http.get(f"/runs/{second}").json()["state"] == "aborted"
    queue_runs_on_from_the_page(page, daemon, second, queued)
    assert page.script_errors == []


def queue_from_the_page(page, active: str) -> list[str]:
    """Three runs started while ``active`` runs wait in the queue: the second moved up, the first
    removed. Returns the two left, in their order."""
    message, queue = page.locator("#message"), page.locator("#queue li")
    page.fill("#count", "1")
    queued = []
    for k in range(3):
        page.click("#start")
        expect(message).to_contain_text(f"queued: position {k + 1}, 1 position; it starts when the runs ahead")
        queued.append(re.search(r"Run (run-\S+) ", message.inner_text()).group(1))
    first, second, third = queued
    expect(page.locator("#run-id")).to_have_text(active)  # the page stays with the run in progress
    expect(page.locator("#queue-summary")).to_have_text("3 runs waiting")
    expect(queue).to_have_count(3)
    expect(run_badge(page, third)).to_have_text("queued #3")
    expect(queue.nth(0).locator("button.up")).to_be_disabled()
    expect(queue.nth(2).locator("button.down")).to_be_disabled()
    queue.nth(1).locator("button.up").click()  # the second first
    expect(queue.nth(0)).to_have_attribute("data-run-id", second)
    expect(run_badge(page, first)).to_have_text("queued #2")
    queue.nth(1).locator("button.remove").click()
    expect(message).to_have_text(f"Run {first} removed from the queue.")
    expect(queue).to_have_count(2)
    expect(run_badge(page, first)).to_have_text("aborted")
    removed = page.locator(f'#runs tr[data-run-id="{first}"]')
    expect(removed).to_contain_text("none: never started")  # no file to download, nothing to process
    expect(removed.locator("button.process")).to_be_disabled()
    expect(page.locator(f'#runs tr[data-run-id="{third}"]')).to_contain_text("not yet taken")
    expect(run_badge(page, third)).to_have_text("queued #2")
    return [second, third]


def queue_runs_on_from_the_page(page, daemon, aborted: str, queued: list[str]) -> None:
    """The aborted run holds the queue, and the page says why; started again, its first run goes,
    and the one behind it starts by itself once that one has completed."""
    expect(page.locator("#queue-held")).to_have_text(f"Held: run {aborted} was aborted")
    expect(run_badge(page, queued[0])).to_have_text("queued #1")
    page.screenshot(path=str(daemon.log_path.parent / "queue.png"), full_page=True)
    page.click("#queue-start")
    expect(page.locator("#queue-held")).to_be_hidden()
    expect(page.locator("#queue-start")).to_be_hidden()
    for run_id in queued:
        expect(run_badge(page, run_id)).to_have_text("complete", timeout=30_000)
    expect(page.locator("#queue-summary")).to_have_text("no run waiting")
    with daemon.client() as http:
        ran = [http.get(f"/runs/{run_id}").json() for run_id in queued]
    assert ran[0]["finished_utc"] <= ran[1]["started_utc"]


def run_badge(page, run_id: str):
    return page.locator(f'#runs tr[data-run-id="{run_id}"] .badge')


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
    expect(page.locator("#frame-caption")).to_contain_text("exposure 1/1000 s")
    assert page.script_errors == []


def test_the_page_shows_each_job_and_links_its_report_ies_and_ray_file(tmp_path, daemon_factory, page, captured):
    from test_worker import Data

    from acquisition.daemon.worker import JobWorker

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
    # The report's figures on the page: the whole light's C-plane polar diagram and each source's
    # polar plot among them, each image loaded.
    expect(page.locator("#results-of")).to_contain_text(f"of run {run.id}, job {job['id']}")
    expect(page.locator('#figures img[alt*="polar"]')).to_have_count(2)
    page.wait_for_function(
        "() => { const imgs = [...document.querySelectorAll('#figures img')];"
        " return imgs.length >= 5 && imgs.every(i => i.complete && i.naturalWidth > 0); }"
    )
    # The whole light's photometric summary above them, as the light model has it.
    summary = httpx.get(f"{daemon.url}/jobs/{job['id']}/photometry", headers=AUTH, timeout=30).json()
    model = json.loads(Path(done.artifacts["light_model"]).read_text())["photometry"]
    assert summary["total_flux"] == model["total_flux"] and summary["beam_angle_deg"] == model["beam_angle_deg"]
    table = page.locator("#photometry")
    expect(table).to_contain_text(f"{summary['total_flux']:.4g} {model['flux_units']}")
    beam = summary["beam_angle_deg"]["C0-C180"]
    expect(table.locator("tr", has_text="beam angle (50 %)")).to_contain_text(f"{beam:.3g}° (C0-C180)")
    expect(table).to_contain_text("% of the flux (θ measured to")
    figures = httpx.get(f"{daemon.url}/jobs/{job['id']}/figures", headers=AUTH, timeout=30).json()
    polar = next(f for f in figures if f["caption"].startswith("Radiant intensity of each source"))
    assert "polar" in polar["alt"]
    png = httpx.get(daemon.url + polar["url"], headers=AUTH, timeout=30)
    assert png.headers["content-type"] == "image/png" and png.content[:8] == b"\x89PNG\r\n\x1a\n"
    assert httpx.get(daemon.url + polar["url"], timeout=30).status_code == 401  # the token guards it
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
    model, what the light files hold beyond the measured θ) go with the next `process` click as
    the job's options, as `POST /runs/{id}/process` takes them; only those that differ from the
    worker's defaults."""
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
    expect(page.locator("#extrapolation")).to_have_value("fitted")
    choices = [
        (
            "always",
            True,
            "polynomial",
            "none",
            True,
            "steps hdr,sources, aperture fitted, sensor distance fitted, polynomial fits, measured range only, "
            "positions with a corrupt frame skipped",
        ),
        ("never", False, "gaussian", "fitted", False, "steps hdr,sources, aperture as described"),
        ("auto", False, "gaussian", "fitted", False, "steps hdr,sources"),
    ]
    for aperture, distance, model, extrapolation, skip, said in choices:
        page.select_option("#fit-aperture", aperture)
        page.set_checked("#fit-sensor-distance", distance)
        page.select_option("#fit-model", model)
        page.select_option("#extrapolation", extrapolation)
        page.set_checked("#ignore-corrupt", skip)
        row.locator("button.process").click()
        expect(message).to_contain_text(f"queued for run {run.id} ({said}).")
    page.screenshot(path=str(tmp_path / "options.png"), full_page=True)
    with daemon.client() as http:
        jobs = sorted(http.get("/jobs", params={"run_id": run.id}).json(), key=lambda job: job["created_utc"])
    options = [
        {
            "fit_aperture": "always",
            "fit_sensor_distance": "always",
            "fit": "polynomial",
            "extrapolation": "none",
            "ignore_corrupt": True,
        },
        {"fit_aperture": "never"},
        {},
    ]
    assert sorted((job["options"] for job in jobs), key=len) == sorted(options, key=len)
    for job in jobs:
        said = next(said for (*_, said), opts in zip(choices, options, strict=False) if opts == job["options"])
        expect(page.locator(f'#jobs tr[data-job-id="{job["id"]}"] td').first).to_have_attribute("title", said)
    data.catalog.close()
    assert page.script_errors == []


def test_the_page_shows_the_labs_runs_with_other_rigs_read_only(
    tmp_path, daemon_factory, page, captured, postgres_server
):
    from test_worker import _finished_run

    from acquisition.daemon.catalog import Catalog

    url = postgres_server.create_database("lab_page")
    configs = {}
    for rig in ("rig-a", "rig-b"):
        config = write_config(tmp_path / f"{rig}.toml", tmp_path / rig)
        config.write_text(f'rig_name = "{rig}"\ncatalog = "{url}"\n' + config.read_text())
        configs[rig] = config
    with Catalog(url, rig="rig-a") as rig_a, Catalog(url, rig="rig-b") as rig_b:
        theirs = _finished_run(rig_a, tmp_path / "rig-a", captured[2])
        ours = _finished_run(rig_b, tmp_path / "rig-b", captured[2])
    daemon = daemon_factory(configs["rig-b"], token=TOKEN)
    open_page(page, daemon)
    expect(page.locator("#rig-name")).to_have_text("of rig rig-b")
    expect(page.locator(f'#runs tr[data-run-id="{ours.id}"]')).to_contain_text("complete")
    expect(page.locator(f'#runs tr[data-run-id="{theirs.id}"]')).to_have_count(0)  # its own rig's runs first
    page.locator("#all-rigs").check()
    row = page.locator(f'#runs tr[data-run-id="{theirs.id}"]')
    expect(row.locator(".badge.rig")).to_have_text("rig-a")
    expect(row.locator("button.process")).to_be_disabled()
    expect(row.locator("button.process")).to_have_attribute("title", "rig rig-a's run: process it from its own daemon")
    mine = page.locator(f'#runs tr[data-run-id="{ours.id}"]')
    expect(mine.locator("button.process")).to_be_enabled()
    expect(mine.locator(".badge.rig")).to_have_count(0)
    assert page.script_errors == []
