"""The catalog of runs and jobs: states, restarts, and races between threads and processes."""

import itertools
import multiprocessing
import os
import pickle
import re
import secrets
import shutil
import tempfile
import threading
import time
from datetime import UTC, datetime, timedelta, timezone
from pathlib import Path

import pytest
from conftest import run_sql, unable

from acquisition.daemon.catalog import (
    ALLOWED_RUN_TRANSITIONS,
    DEFAULT_RIG,
    JOB_STATES,
    RUN_STATES,
    SCHEMA_VERSION,
    ActiveRunError,
    Catalog,
    CatalogError,
    InvalidTransitionError,
    JobClaimError,
    NotQueuedError,
    OtherRigError,
    UnknownJobError,
    UnknownRunError,
)

T0 = datetime(2026, 11, 21, 13, 45, 1, tzinfo=UTC)


class FakeClock:
    """A clock the test moves by hand."""

    def __init__(self, start: datetime = T0):
        self.now = start
        self._lock = threading.Lock()

    def __call__(self) -> datetime:
        with self._lock:
            return self.now

    def advance(self, seconds: float) -> None:
        with self._lock:
            self.now += timedelta(seconds=seconds)


@pytest.fixture
def clock():
    return FakeClock()


@pytest.fixture
def db(catalog_url):
    """A new catalog's location: every test here runs on SQLite and on PostgreSQL."""
    return catalog_url


@pytest.fixture
def cat(db, clock):
    catalog = Catalog(db, clock=clock)
    yield catalog
    catalog.close()


def _new_run(cat, n=10, **request):
    return cat.create_run(preset="quick", path_for=lambda rid: f"/data/{rid}.h5", n_positions=n, request=request)


def _run_in(cat, state):
    """A new run brought to ``state`` through allowed transitions."""
    run = _new_run(cat)
    path = {
        "queued": [],
        "running": ["running"],
        "paused": ["running", "paused"],
        "complete": ["running", "complete"],
        "aborted": ["aborted"],
        "failed": ["running", "failed"],
        "interrupted": ["running", "interrupted"],
    }[state]
    for step in path:
        run = cat.transition_run(run.id, step)
    return run


# --- runs --------------------------------------------------------------------------------
def test_create_get_list_runs_newest_first(cat, clock):
    ids = []
    for k in range(3):
        run = _new_run(cat, n=5 + k, k=k, nested={"exposures": [0.001, 0.01]})
        assert re.fullmatch(r"run-20261121-1345\d\d-[0-9a-f]{4}", run.id)
        assert run.state == "queued"
        assert run.path == f"/data/{run.id}.h5"
        assert run.created_utc == run.updated_utc == clock.now
        assert run.n_positions == 5 + k and run.positions_done == 0
        assert run.request == {"k": k, "nested": {"exposures": [0.001, 0.01]}}
        assert run.started_utc is None and run.finished_utc is None and run.eta_s is None
        ids.append(run.id)
        cat.transition_run(run.id, "aborted")
    assert len(set(ids)) == 3
    assert cat.get_run(ids[1]).request["k"] == 1
    assert [r.id for r in cat.list_runs()] == ids[::-1]
    assert [r.id for r in cat.list_runs(limit=2)] == ids[:0:-1]
    assert cat.list_runs(state="running") == []
    assert len(cat.list_runs(state="aborted")) == 3
    with pytest.raises(UnknownRunError, match="run-nope"):
        cat.get_run("run-nope")
    with pytest.raises(CatalogError, match="unknown run state 'done'"):
        cat.list_runs(state="done")


def test_create_run_refuses_bad_input_and_queues_runs_behind_the_one_in_progress(cat):
    with pytest.raises(CatalogError, match="n_positions"):
        cat.create_run(preset="p", path_for=None, n_positions=0, request={})
    with pytest.raises(CatalogError, match="not plain JSON"):
        cat.create_run(preset="p", path_for=None, n_positions=3, request={"x": float("nan")})
    run = cat.create_run(preset=None, path_for=None, n_positions=3, request={})
    assert run.path is None and run.preset is None and run.queue_position == 1
    second = _new_run(cat)
    assert second.state == "queued" and second.queue_position == 2
    cat.transition_run(run.id, "running")  # it leaves the queue
    assert cat.get_run(run.id).queue_position is None and cat.get_run(second.id).queue_position == 1
    with pytest.raises(ActiveRunError, match=f"run {run.id} is running"):
        cat.transition_run(second.id, "running")  # one run in progress at a time
    cat.transition_run(run.id, "complete")
    assert cat.transition_run(second.id, "running").state == "running"


def test_the_queue_keeps_its_order_and_its_hold_across_a_reopen(db, clock):
    cat = Catalog(db, clock=clock)
    first, second, third = (_new_run(cat) for _ in range(3))
    assert [r.id for r in cat.reorder_queue([third.id])] == [third.id, first.id, second.id]
    with pytest.raises(CatalogError, match=f"run '{first.id}' is named twice"):
        cat.reorder_queue([first.id, first.id])
    with pytest.raises(UnknownRunError):
        cat.reorder_queue(["run-nope"])
    assert cat.queue_hold() is None
    cat.hold_queue("run run-x failed: alarm")
    cat.close()
    clock.advance(60)
    cat = Catalog(db, clock=clock)  # the daemon restarts
    try:
        assert cat.mark_interrupted() == []
        assert [(r.id, r.queue_position) for r in cat.queued_runs()] == [(third.id, 1), (first.id, 2), (second.id, 3)]
        assert cat.queue_hold() == ("run run-x failed: alarm", clock.now - timedelta(seconds=60))
        removed = cat.remove_from_queue(first.id, "removed from the queue by the operator")
        assert (removed.state, removed.last_error, removed.queue_position) == (
            "aborted",
            "removed from the queue by the operator",
            None,
        )
        assert removed.finished_utc == clock.now and removed.started_utc is None
        with pytest.raises(NotQueuedError, match=f"cannot remove it from the queue: run {first.id} is aborted"):
            cat.remove_from_queue(first.id, "again")
        with pytest.raises(NotQueuedError, match="cannot reorder the queue"):
            cat.reorder_queue([first.id])
        assert cat.queue_hold() is not None  # runs still wait
        cat.remove_from_queue(third.id, "gone")
        cat.remove_from_queue(second.id, "gone")
        assert cat.queue_hold() is None  # the hold goes with the queue's last run
        cat.hold_queue("held")
        cat.release_queue()
        assert cat.queue_hold() is None
    finally:
        cat.close()


def test_every_transition_follows_the_table(cat):
    assert set(ALLOWED_RUN_TRANSITIONS) == set(RUN_STATES)
    for source, target in itertools.product(RUN_STATES, RUN_STATES):
        run = _run_in(cat, source)
        assert run.state == source
        if target in ALLOWED_RUN_TRANSITIONS[source]:
            assert cat.transition_run(run.id, target).state == target
        else:
            with pytest.raises(InvalidTransitionError) as info:
                cat.transition_run(run.id, target)
            assert info.value.from_state == source and info.value.to_state == target
            assert cat.get_run(run.id).state == source
        # Leave no active run behind for the next pair.
        if cat.get_run(run.id).state in ("queued", "running", "paused"):
            cat.transition_run(run.id, "aborted")


def test_invalid_transition_message_names_the_run_and_both_states(cat):
    run = _run_in(cat, "complete")
    with pytest.raises(InvalidTransitionError) as info:
        cat.transition_run(run.id, "running")
    message = str(info.value)
    assert "\n" not in message
    assert run.id in message and "from complete to running" in message and "final" in message
    with pytest.raises(CatalogError, match="unknown run state 'done'"):
        cat.transition_run(run.id, "done")
    with pytest.raises(UnknownRunError):
        cat.transition_run("run-nope", "running")
    # The errors survive a trip to another process.
    again = pickle.loads(pickle.dumps(info.value))
    assert type(again) is InvalidTransitionError and str(again) == message


def test_transitions_set_start_finish_and_error(cat, clock):
    run = _new_run(cat)
    clock.advance(5)
    run = cat.transition_run(run.id, "running")
    started = clock.now
    assert run.started_utc == started and run.finished_utc is None
    clock.advance(60)
    run = cat.transition_run(run.id, "failed", error="arm: move_to: alarm 0x0010: overtravel")
    assert run.finished_utc == clock.now and run.last_error.startswith("arm: move_to")
    clock.advance(60)
    run = cat.transition_run(run.id, "running")  # resumed after the fault was cleared
    assert run.started_utc == started and run.finished_utc is None
    assert run.last_error is None  # cleared: a resumed run shows a new error only
    run = cat.transition_run(run.id, "complete")
    assert run.finished_utc == clock.now and run.updated_utc == clock.now


def test_resuming_a_run_while_another_is_active_is_refused(cat):
    old = _run_in(cat, "interrupted")
    new = _run_in(cat, "running")
    with pytest.raises(ActiveRunError, match=new.id):
        cat.transition_run(old.id, "running")
    cat.transition_run(new.id, "complete")
    assert cat.transition_run(old.id, "running").state == "running"


def test_racing_transitions_exactly_one_wins(db, clock):
    """Two threads, each with its own connection, end the same running run differently."""
    cats = [Catalog(db, clock=clock) for _ in range(2)]
    targets = ("complete", "aborted")
    try:
        for _ in range(15):
            run = _run_in(cats[0], "running")
            barrier = threading.Barrier(2)
            outcomes = [None, None]

            def end(k, barrier=barrier, outcomes=outcomes, run=run):
                barrier.wait()
                try:
                    outcomes[k] = cats[k].transition_run(run.id, targets[k]).state
                except InvalidTransitionError as exc:
                    outcomes[k] = exc

            threads = [threading.Thread(target=end, args=(k,)) for k in range(2)]
            for t in threads:
                t.start()
            for t in threads:
                t.join(10)
            winners = [o for o in outcomes if isinstance(o, str)]
            losers = [o for o in outcomes if isinstance(o, InvalidTransitionError)]
            assert len(winners) == 1 and len(losers) == 1, outcomes
            assert cats[0].get_run(run.id).state == winners[0]
            assert losers[0].from_state == winners[0]
            assert f"from {winners[0]} to" in str(losers[0])
    finally:
        for c in cats:
            c.close()


def test_active_run_and_mark_interrupted_after_restart(db, clock):
    cat = Catalog(db, clock=clock)
    assert cat.active_run() is None
    done = _run_in(cat, "complete")
    run = _run_in(cat, "running")
    cat.update_progress(run.id, positions_done=3, current_position=3, seconds_per_position=4.0)
    assert cat.active_run().id == run.id
    cat.close()
    with pytest.raises(CatalogError, match="closed"):
        cat.get_run(run.id)

    clock.advance(3600)
    cat = Catalog(db, clock=clock)  # the daemon restarts on the same file
    try:
        survived = cat.get_run(run.id)
        assert survived.state == "running" and survived.positions_done == 3
        assert cat.get_run(done.id).state == "complete"
        assert cat.mark_interrupted() == [run.id]
        assert cat.mark_interrupted() == []
        after = cat.get_run(run.id)
        assert after.state == "interrupted" and after.updated_utc == clock.now
        assert after.positions_done == 3 and after.current_position == 3
        assert cat.active_run() is None
        assert cat.transition_run(run.id, "running").state == "running"  # resume
        assert cat.active_run().id == run.id
    finally:
        cat.close()


def test_mark_interrupted_catches_paused_and_keeps_the_queue(cat):
    queued = _run_in(cat, "queued")
    assert cat.active_run() is None  # a queued run waits: it is not in progress
    paused = _run_in(cat, "paused")
    later = _new_run(cat)
    assert cat.active_run().id == paused.id
    assert cat.mark_interrupted() == [paused.id]
    assert [r.id for r in cat.queued_runs()] == [queued.id, later.id]
    states = {r.id: r.state for r in cat.list_runs()}
    assert states == {queued.id: "queued", paused.id: "interrupted", later.id: "queued"}


def test_progress_and_eta(cat, clock):
    run = _new_run(cat, n=10)
    cat.transition_run(run.id, "running")
    clock.advance(30)
    cat.update_progress(
        run.id, positions_done=4, current_position=4, seconds_per_position=2.5, exposures_per_position=5
    )
    run = cat.get_run(run.id)
    assert (run.positions_done, run.current_position, run.exposures_per_position) == (4, 4, 5)
    assert run.updated_utc == clock.now
    assert run.eta_s == pytest.approx(15.0)
    assert run.model_dump(mode="json")["eta_s"] == pytest.approx(15.0)
    # None leaves the average and the exposures as they were.
    cat.update_progress(run.id, positions_done=5, current_position=None)
    run = cat.get_run(run.id)
    assert run.current_position is None and run.seconds_per_position == 2.5 and run.exposures_per_position == 5
    assert run.eta_s == pytest.approx(12.5)
    # The arm's place alone (the run thread's report): the writer's count stays.
    cat.update_progress(run.id, current_position=6)
    run = cat.get_run(run.id)
    assert (run.positions_done, run.current_position) == (5, 6)
    assert cat.transition_run(run.id, "paused").eta_s is None  # no ETA unless running
    with pytest.raises(CatalogError, match="positions_done 11 > n_positions 10"):
        cat.update_progress(run.id, positions_done=11, current_position=None)
    with pytest.raises(CatalogError, match="current_position 10 >= n_positions 10"):
        cat.update_progress(run.id, positions_done=10, current_position=10)
    with pytest.raises(CatalogError, match="seconds_per_position"):
        cat.update_progress(run.id, positions_done=5, current_position=5, seconds_per_position=-1.0)
    with pytest.raises(UnknownRunError):
        cat.update_progress("run-nope", positions_done=0, current_position=None)


def test_the_clock_must_be_timezone_aware(db):
    with pytest.raises(CatalogError, match="timezone-aware"):
        Catalog(db, clock=lambda: datetime(2026, 1, 1))
    cet = timezone(timedelta(hours=1))
    cat = Catalog(db, clock=lambda: datetime(2026, 1, 1, 13, 0, tzinfo=cet))
    try:
        assert _new_run(cat).created_utc == datetime(2026, 1, 1, 12, 0, tzinfo=UTC)
    finally:
        cat.close()


def test_schema_version_is_recorded_and_a_newer_one_refused(db, clock):
    Catalog(db, clock=clock).close()
    Catalog(db, clock=clock).close()  # reopening does not migrate twice
    versions, _ = run_sql(
        db,
        "SELECT version FROM schema_version ORDER BY version",
        ("INSERT INTO schema_version VALUES (?, 'later')", (SCHEMA_VERSION + 1,)),
    )
    assert versions == [(v,) for v in range(1, SCHEMA_VERSION + 1)]
    if not db.startswith("postgresql://"):
        assert run_sql(db, "PRAGMA journal_mode") == [[("wal",)]]
    with pytest.raises(CatalogError, match=f"schema version {SCHEMA_VERSION + 1}, newer"):
        Catalog(db, clock=clock)


def test_a_server_that_cannot_be_reached_is_one_line_without_its_password():
    with pytest.raises(CatalogError, match=r"cannot open catalog postgresql://lab@127\.0\.0\.1:9/catalog: ") as caught:
        Catalog("postgresql://lab:s3cret@127.0.0.1:9/catalog", busy_timeout_s=1)
    assert "s3cret" not in str(caught.value) and "\n" not in str(caught.value)
    with pytest.raises(CatalogError, match="unknown URL scheme 'mysql'"):
        Catalog("mysql://lab@host/catalog")


def test_a_file_that_is_not_a_catalog_is_refused(tmp_path):
    junk = tmp_path / "junk.sqlite"
    junk.write_bytes(b"this is not a database" * 100)
    with pytest.raises(CatalogError, match="cannot open catalog .*junk.sqlite"):
        Catalog(junk)
    with pytest.raises(CatalogError, match="cannot open catalog"):
        Catalog(tmp_path / "missing-dir" / "catalog.sqlite")


# --- jobs --------------------------------------------------------------------------------
def test_create_get_list_jobs(cat, clock):
    assert JOB_STATES == ("queued", "running", "complete", "failed")
    with pytest.raises(UnknownRunError, match="run-nope"):
        cat.create_job("run-nope")
    run = _run_in(cat, "complete")
    job = cat.create_job(run.id)
    assert re.fullmatch(r"job-20261121-134501-[0-9a-f]{4}", job.id)
    assert (job.run_id, job.state, job.steps, job.options, job.progress) == (run.id, "queued", "hdr,sources", {}, 0.0)
    assert job.claimed_by is None and job.heartbeat_utc is None and job.created_utc == clock.now
    other = cat.create_job(run.id, steps="hdr, fit", options={"sources": 5})
    assert other.steps == "hdr,fit" and cat.get_job(other.id).options == {"sources": 5}
    assert [j.id for j in cat.list_jobs()] == [other.id, job.id]
    assert [j.id for j in cat.list_jobs(run.id, limit=1)] == [other.id]
    with pytest.raises(UnknownRunError):
        cat.list_jobs("run-nope")
    with pytest.raises(UnknownJobError, match="job-nope"):
        cat.get_job("job-nope")
    with pytest.raises(CatalogError, match="not a step name"):
        cat.create_job(run.id, steps="hdr,,fit")
    with pytest.raises(CatalogError, match="twice"):
        cat.create_job(run.id, steps="hdr,hdr")


def test_claim_takes_the_oldest_queued_job(cat):
    run = _run_in(cat, "complete")
    jobs = [cat.create_job(run.id) for _ in range(3)]  # same timestamp: order by creation
    assert [cat.claim_job("w1").id for _ in range(3)] == [j.id for j in jobs]
    assert cat.claim_job("w1") is None


def _claim_until_empty(path, worker_id, start, results):
    """A worker process: claim and finish jobs until none is left, report the ids (or the error)."""
    try:
        cat = Catalog(path)
        start.wait(30)  # both workers have opened the catalog: the race starts now
        claimed = []
        while (job := cat.claim_job(worker_id)) is not None:
            claimed.append(job.id)
            time.sleep(0.005)  # some work, so that both workers are claiming at the same time
            cat.finish_job(job.id, worker_id=worker_id, result_dir=f"/results/{job.id}")
        cat.close()
        results.put((worker_id, claimed))
    except BaseException as exc:  # noqa: BLE001 - report it: the parent would otherwise wait for nothing
        results.put((worker_id, f"{type(exc).__name__}: {exc}"))


def test_claim_job_is_atomic_across_processes(db):
    cat = Catalog(db)
    run = _run_in(cat, "complete")
    job_ids = {cat.create_job(run.id).id for _ in range(20)}
    ctx = multiprocessing.get_context("spawn")
    start, results = ctx.Barrier(2), ctx.Queue()
    workers = [ctx.Process(target=_claim_until_empty, args=(str(db), f"w{k}", start, results)) for k in range(2)]
    for w in workers:
        w.start()
    reports = dict(results.get(timeout=60) for _ in workers)
    for w in workers:
        w.join(30)
        assert w.exitcode == 0
    assert all(isinstance(ids, list) for ids in reports.values()), reports
    claimed = reports["w0"] + reports["w1"]
    assert len(claimed) == len(set(claimed)) == 20  # every job claimed exactly once
    assert set(claimed) == job_ids
    for job in cat.list_jobs(run.id):
        assert job.state == "complete" and job.progress == 1.0
        assert job.id in reports[job.claimed_by] and job.result_dir == f"/results/{job.id}"
    cat.close()


def test_a_catalog_opened_before_fork_refuses_the_child(db):
    if "fork" not in multiprocessing.get_all_start_methods():
        pytest.skip("no fork on this platform")
    cat = Catalog(db)
    run = _new_run(cat)
    ctx = multiprocessing.get_context("fork")
    results = ctx.Queue()

    def child():
        try:
            cat.get_run(run.id)
            results.put("used the parent's connection")
        except CatalogError as exc:
            own = Catalog(db)
            results.put((str(exc), own.get_run(run.id).state))
            own.close()

    p = ctx.Process(target=child)
    p.start()
    message, state = results.get(timeout=30)
    p.join(10)
    assert "open a new Catalog" in message and state == "queued"
    assert cat.get_run(run.id).state == "queued"  # the parent's connection still works
    cat.close()


def test_heartbeat_and_requeue_stale_jobs(cat, clock):
    run = _run_in(cat, "complete")
    a, b = cat.create_job(run.id), cat.create_job(run.id)
    assert cat.claim_job("w1").id == a.id
    assert cat.claim_job("w2").id == b.id
    clock.advance(20)
    cat.heartbeat(a.id, "w1", progress=0.25)
    job = cat.get_job(a.id)
    assert job.heartbeat_utc == clock.now and job.progress == 0.25
    clock.advance(20)  # w1 beat 20 s ago, w2 40 s ago
    assert cat.requeue_stale_jobs(30) == [b.id]
    requeued = cat.get_job(b.id)
    assert requeued.state == "queued" and requeued.claimed_by is None and requeued.heartbeat_utc is None
    assert cat.get_job(a.id).state == "running"
    # The dead worker comes back: it no longer holds the job.
    with pytest.raises(JobClaimError, match=f"job {b.id} is queued, claimed by nobody, not by w2"):
        cat.heartbeat(b.id, "w2")
    again = cat.claim_job("w3")
    assert again.id == b.id and again.claimed_by == "w3" and again.progress == 0.0
    with pytest.raises(JobClaimError, match="claimed by w3, not by w2"):
        cat.heartbeat(b.id, "w2", progress=0.5)
    with pytest.raises(JobClaimError, match="claimed by w3"):
        cat.finish_job(b.id, worker_id="w2")
    with pytest.raises(UnknownJobError):
        cat.heartbeat("job-nope", "w1")
    with pytest.raises(CatalogError, match="progress"):
        cat.heartbeat(a.id, "w1", progress=1.5)
    assert cat.requeue_stale_jobs(30) == []


def test_finish_job(cat):
    run = _run_in(cat, "complete")
    ok, bad = cat.create_job(run.id), cat.create_job(run.id)
    with pytest.raises(InvalidTransitionError, match=f"{ok.id}: cannot go from queued to complete"):
        cat.finish_job(ok.id)
    cat.claim_job("w1")
    cat.claim_job("w1")
    done = cat.finish_job(ok.id, result_dir="/data/results/x", worker_id="w1")
    assert (done.state, done.progress, done.result_dir, done.error) == ("complete", 1.0, "/data/results/x", None)
    cat.heartbeat(bad.id, "w1", progress=0.4)
    failed = cat.finish_job(bad.id, error="trace: no ball found in frame 12")
    assert (failed.state, failed.progress, failed.error) == ("failed", 0.4, "trace: no ball found in frame 12")
    with pytest.raises(InvalidTransitionError, match="from complete to failed"):
        cat.finish_job(ok.id, error="late")
    with pytest.raises(UnknownJobError):
        cat.finish_job("job-nope")


def test_a_version_1_catalog_is_migrated_and_keeps_its_jobs(db, clock):
    # The version-1 schema, as the first release wrote it, with one job in it.
    from acquisition.daemon.catalog.schema import MIGRATIONS

    run_sql(
        db,
        "CREATE TABLE schema_version (version INTEGER PRIMARY KEY, applied_utc TEXT NOT NULL)",
        *MIGRATIONS[0],
        "INSERT INTO schema_version VALUES (1, '2026-11-20T00:00:00.000000Z')",
        "INSERT INTO runs (id, seq, created_utc, updated_utc, state, n_positions, positions_done, request_json) "
        "VALUES ('run-old', 1, '2026-11-19T00:00:00.000000Z', '2026-11-19T00:00:00.000000Z', 'complete', 3, 3, '{}')",
        # a run left queued: it keeps its turn in the queue
        "INSERT INTO runs (id, seq, created_utc, updated_utc, state, n_positions, positions_done, request_json) "
        "VALUES ('run-waits', 2, '2026-11-20T00:00:00.000000Z', '2026-11-20T00:00:00.000000Z', 'queued', 3, 0, "
        "'{}')",
        "INSERT INTO jobs (id, seq, run_id, created_utc, updated_utc, state, steps, options_json, progress) "
        "VALUES ('job-old', 1, 'run-old', '2026-11-20T00:00:00.000000Z', '2026-11-20T00:00:00.000000Z', "
        "'queued', 'hdr,trace,fit', '{}', 0)",
    )
    cat = Catalog(db, clock=clock)
    try:
        job = cat.get_job("job-old")
        assert (job.steps, job.artifacts, job.message, job.not_before_utc) == ("hdr,trace,fit", {}, None, None)
        assert cat.claim_job("w1").id == "job-old"
        assert [(r.id, r.queue_position) for r in cat.queued_runs()] == [("run-waits", 1)]
        assert cat.queue_hold() is None
        # The runs before rigs had names are the default rig's; new rows number on after the old.
        assert cat.get_run("run-old").rig == cat.get_job("job-old").rig == DEFAULT_RIG
        newer = _run_in(cat, "complete")
        cat.create_job(newer.id)
        assert [r.id for r in cat.list_runs()][-2:] == ["run-waits", "run-old"]
        assert [j.id for j in cat.list_jobs()][-1] == "job-old"
    finally:
        cat.close()


def test_a_released_job_waits_without_holding_up_the_queue(cat, clock):
    run = _run_in(cat, "complete")
    first, second = cat.create_job(run.id), cat.create_job(run.id)
    assert cat.claim_job("w1").id == first.id
    back = cat.release_job(first.id, "w1", message="waiting: run is running", retry_after_s=30)
    assert (back.state, back.claimed_by, back.message) == ("queued", None, "waiting: run is running")
    assert back.not_before_utc == clock.now + timedelta(seconds=30)
    assert cat.claim_job("w1").id == second.id  # the waiting job is skipped
    assert cat.claim_job("w1") is None
    clock.advance(31)
    again = cat.claim_job("w2")
    assert again.id == first.id and again.not_before_utc is None
    with pytest.raises(JobClaimError, match="claimed by w2, not by w1"):
        cat.release_job(first.id, "w1", message="nope")
    cat.finish_job(second.id, worker_id="w1")
    with pytest.raises(InvalidTransitionError, match="from complete to queued"):
        cat.release_job(second.id, "w1", message="late")
    with pytest.raises(CatalogError, match="message"):
        cat.release_job(first.id, "w2", message="two\nlines")


def test_finish_job_records_artifacts_and_heartbeat_a_note(cat):
    run = _run_in(cat, "complete")
    job = cat.create_job(run.id, options={"partial": True})
    cat.claim_job("w1")
    cat.heartbeat(job.id, "w1", progress=0.5, message="positions 33 of 66")
    assert cat.get_job(job.id).message == "positions 33 of 66"
    cat.heartbeat(job.id, "w1", progress=0.6)  # the note stays
    assert cat.get_job(job.id).message == "positions 33 of 66"
    with pytest.raises(CatalogError, match="artifacts must map kinds"):
        cat.finish_job(job.id, artifacts={"Report!": "/x"})
    done = cat.finish_job(
        job.id,
        worker_id="w1",
        result_dir="/data/runs",
        artifacts={"report": "/data/runs/r.report.html", "ies": "/data/runs/r.ies"},
        message="3 of 66 positions (partial run)",
    )
    assert done.artifacts == {"report": "/data/runs/r.report.html", "ies": "/data/runs/r.ies"}
    assert done.message == "3 of 66 positions (partial run)" and done.options == {"partial": True}


def test_a_requeued_job_says_why(cat, clock):
    run = _run_in(cat, "complete")
    job = cat.create_job(run.id)
    cat.claim_job("w1")
    clock.advance(100)
    assert cat.requeue_stale_jobs(30) == [job.id]
    assert "stopped sending heartbeats" in cat.get_job(job.id).message


def test_concurrent_writes_from_threads_do_not_lock(db, clock):
    """Six threads share one Catalog, two more have their own connection to the file."""
    shared = Catalog(db, clock=clock)
    run = _run_in(shared, "running")
    own = [Catalog(db, clock=clock) for _ in range(2)]
    errors = []
    barrier = threading.Barrier(8)

    def work(k, cat):
        try:
            barrier.wait()
            for i in range(25):
                cat.update_progress(run.id, positions_done=i % 10, current_position=i % 10, seconds_per_position=1.0)
                job = cat.create_job(run.id, options={"thread": k, "i": i})
                cat.get_run(run.id)
                cat.list_jobs(run.id, limit=5)
                claimed = cat.claim_job(f"w{k}")
                if claimed is not None:
                    cat.heartbeat(claimed.id, f"w{k}", progress=0.5)
                    cat.finish_job(claimed.id, worker_id=f"w{k}")
                assert job.options["thread"] == k
        except Exception as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(k, shared if k < 6 else own[k - 6])) for k in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    try:
        assert errors == []
        jobs = shared.list_jobs(run.id, limit=1000)
        assert len(jobs) == 8 * 25
        assert {j.state for j in jobs} <= {"queued", "complete"}
        assert sum(j.state == "complete" for j in jobs) >= 1
    finally:
        for c in [shared, *own]:
            c.close()


# --- several rigs, one catalog -------------------------------------------------------------
def test_each_rig_has_its_runs_queue_and_jobs_and_reads_the_others(db, clock):
    a, b = Catalog(db, clock=clock, rig="rig-a"), Catalog(db, clock=clock, rig="rig-b")
    try:
        a1, a2 = _new_run(a), _new_run(a)
        b1 = _new_run(b)
        assert (a1.rig, b1.rig) == ("rig-a", "rig-b")
        assert b1.queue_position == 1  # each rig's queue is its own
        a.transition_run(a1.id, "running")
        assert b.transition_run(b1.id, "running").state == "running"  # one run in progress per rig
        assert a.active_run().id == a1.id and b.active_run().id == b1.id
        a.hold_queue("lamp warming up")
        assert a.queue_hold()[0] == "lamp warming up" and b.queue_hold() is None
        assert [r.id for r in a.queued_runs()] == [a2.id] and b.queued_runs() == []
        # The lab's runs, read from either rig; another rig's runs, by name.
        assert {r.id for r in b.list_runs(rig=None)} == {a1.id, a2.id, b1.id}
        assert [r.id for r in b.list_runs(rig="rig-a")] == [a2.id, a1.id]
        assert [r.id for r in b.list_runs()] == [b1.id]
        assert b.get_run(a1.id).state == "running" and b.rigs() == ["rig-a", "rig-b"]
        # ... and never changed by the rig that is not theirs.
        for change in (
            lambda: b.transition_run(a1.id, "aborted"),
            lambda: b.create_job(a1.id),
            lambda: b.remove_from_queue(a2.id, "no"),
            lambda: b.reorder_queue([a2.id]),
            lambda: b.update_progress(a1.id, positions_done=1, current_position=1),
        ):
            with pytest.raises(OtherRigError, match="belongs to rig 'rig-a'"):
                change()
        assert a.get_run(a1.id).state == "running" and a.get_run(a2.id).queue_position == 1
        refused = f"cannot make it aborted: run {a1.id} belongs to rig 'rig-a'; rig 'rig-b' can only read it"
        with pytest.raises(OtherRigError, match=refused):
            b.transition_run(a1.id, "aborted")
        # A daemon that restarts interrupts only its own rig's runs.
        assert Catalog(db, clock=clock, rig="rig-b").mark_interrupted() == [b1.id]
        assert a.get_run(a1.id).state == "running"
        # Jobs: each rig lists its own; a worker claims any rig's, or those of the rigs it serves.
        ja, jb = a.create_job(a1.id), b.create_job(b1.id)
        assert [j.id for j in a.list_jobs()] == [ja.id] and {j.id for j in a.list_jobs(rig=None)} == {ja.id, jb.id}
        assert a.claim_job("w1", rigs=["rig-b"]).id == jb.id
        assert a.claim_job("w1", rigs=["rig-b"]) is None
        assert b.claim_job("w2").id == ja.id and ja.rig == "rig-a"
        with pytest.raises(CatalogError, match="not a rig's name"):
            Catalog(db, rig="Rig A")
        # Where each rig's daemon answers, for the workers that fetch its run files.
        assert b.daemon_url("rig-a") is None
        a.register_daemon("http://rig-a.lab:8000/")
        a.register_daemon("http://10.0.0.7:8000")  # it moved: the last word counts
        assert b.daemon_url("rig-a") == "http://10.0.0.7:8000" and b.daemon_url("rig-c") is None
        with pytest.raises(CatalogError, match="http:// or https://"):
            a.register_daemon("ftp://rig-a.lab")
        assert a.queue_hold()[0] == "lamp warming up"  # the same row keeps the queue's hold
    finally:
        a.close()
        b.close()


def test_a_catalog_survives_its_server_restarting():
    """PostgreSQL restarts under an open catalog: what was begun before is kept, the next
    operations reconnect, and an operation while it is down fails in one line (503)."""
    from acquisition.daemon.catalog import CatalogUnavailableError
    from acquisition.daemon.catalog.throwaway_server import ThrowawayPostgres

    with ThrowawayPostgres() as server:
        cat = Catalog(server.create_database("restarts"), busy_timeout_s=2)
        try:
            run = _run_in(cat, "running")
            server.restart()
            assert cat.get_run(run.id).state == "running"  # reconnected on its own
            job = cat.create_job(run.id)
            server.stop()
            with pytest.raises(CatalogUnavailableError, match=r"cannot reach the catalog postgresql://.*") as down:
                cat.claim_job("w1")
            assert "\n" not in str(down.value)
            server.start()
            assert cat.claim_job("w1").id == job.id
        finally:
            cat.close()


def test_a_full_disk_under_postgresql_is_a_507_and_a_read_only_server_a_503(tmp_path, postgres_server):
    """The catalog's database in a tablespace on a 16 MB tmpfs: once it is full, a write is a
    one-line CatalogFullError (507) and what was written stays readable; a server made
    read-only refuses writes as unavailable (503)."""
    import pwd
    import subprocess

    import psycopg

    from acquisition.daemon.catalog import CatalogFullError, CatalogUnavailableError

    small = Path(tempfile.mkdtemp(prefix="mirrorgonio-small-"))
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=16m", "tmpfs", str(small)], capture_output=True)
    if mounted.returncode != 0:
        unable(f"a small file system needs mount: {mounted.stderr.decode().strip()}")
    try:
        if os.geteuid() == 0:
            user = pwd.getpwnam("postgres")
            os.chown(small, user.pw_uid, user.pw_gid)
        with psycopg.connect(postgres_server.url(), autocommit=True) as admin:
            admin.execute(f"CREATE TABLESPACE small_{os.getpid()} LOCATION '{small}'")
            admin.execute(f"CREATE DATABASE full_{os.getpid()} TABLESPACE small_{os.getpid()}")
        cat = Catalog(postgres_server.url(f"full_{os.getpid()}"))
        try:
            run = _run_in(cat, "complete")
            with pytest.raises(CatalogFullError, match=r"^no space left on device writing the catalog postgresql://"):
                for k in range(10_000):  # 100 kB a job that does not compress: about 160 fill it
                    cat.create_job(run.id, options={"k": k, "padding": secrets.token_hex(50_000)})
            assert cat.get_run(run.id).state == "complete" and len(cat.list_jobs(run.id, limit=10)) == 10
            with psycopg.connect(postgres_server.url(), autocommit=True) as admin:
                admin.execute(f"ALTER DATABASE full_{os.getpid()} SET default_transaction_read_only = on")
                admin.execute(  # the setting applies to new sessions: the catalog's is ended, it reconnects
                    "SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE datname = %s",
                    (f"full_{os.getpid()}",),
                )
            with pytest.raises(CatalogUnavailableError, match="cannot be written"):
                cat.hold_queue("read-only now")
            assert cat.get_run(run.id).state == "complete"
        finally:
            cat.close()
        with psycopg.connect(postgres_server.url(), autocommit=True) as admin:
            admin.execute(f"DROP DATABASE full_{os.getpid()}")
            admin.execute(f"DROP TABLESPACE small_{os.getpid()}")
    finally:
        subprocess.run(["umount", "-l", str(small)], capture_output=True)
        shutil.rmtree(small, ignore_errors=True)


def test_a_rig_lock_held_past_the_busy_timeout_is_a_503_and_a_bug_stays_a_bug(postgres_server):
    """Another session holds the rig's advisory lock (a daemon stuck mid-write): a change to the
    rig's runs waits ``busy_timeout_s``, then fails as unavailable, as SQLite's "database is
    locked" does; a constraint broken by hand is PostgreSQL's own error, not a storage one."""
    import psycopg

    from acquisition.daemon.catalog import CatalogUnavailableError

    url = postgres_server.create_database(f"locked_{os.getpid()}")
    cat = Catalog(url, rig="rig-a", busy_timeout_s=0.5)
    try:
        run = _new_run(cat)
        with psycopg.connect(url, autocommit=True) as other, other.transaction():
            other.execute("SELECT pg_advisory_xact_lock(hashtext('mirrorgonio:rig:rig-a'))")
            started = time.monotonic()
            with pytest.raises(CatalogUnavailableError, match="writing failed: canceling statement due to lock"):
                cat.transition_run(run.id, "running")
            assert 0.4 < time.monotonic() - started < 5
            assert cat.claim_job("w1") is None  # the jobs take no rig lock: workers go on
        assert cat.transition_run(run.id, "running").state == "running"
        with psycopg.connect(url, autocommit=True) as other:
            other.execute("ALTER TABLE runs ADD CONSTRAINT few CHECK (n_positions < 50)")
        with pytest.raises(psycopg.errors.CheckViolation):
            _new_run(cat, n=60)
    finally:
        cat.close()
