"""The run engine: one rig's runs, and the requests that start, pause, resume, abort and queue them.

One run in progress at a time per rig; the runs asked for meanwhile wait in a queue, in an
order the operator may change (``docs/daemon.md``, "The queue of runs";
:mod:`acquisition.daemon.run_queue`). States: queued → running ⇄ paused → complete | aborted |
failed, and interrupted for a run whose daemon died (resumable, as is a failed run once its
fault is cleared). A run that completes starts the next queued one; one that fails or is
aborted holds the queue, with the reason, until a run is resumed or the queue is started again.

What a request becomes is worked out once, before anything moves
(:mod:`acquisition.daemon.run_preflight`, into a :class:`~acquisition.daemon.run_plan.RunPlan`);
each run is taken by its own thread (:mod:`acquisition.daemon.run_thread`): the sweep, the
calibration frames, the writer behind the arm, the run's end.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

from pydantic import ValidationError

from acquisition.daemon.catalog import Catalog, OtherRigError, RunRecord
from acquisition.daemon.catalog.pending import PendingEnds
from acquisition.daemon.devices import Devices
from acquisition.daemon.models import RunRequest
from acquisition.daemon.run_control import ProgressEvents, RunConflictError, RunEngineError
from acquisition.daemon.run_plan import RunPlan
from acquisition.daemon.run_preflight import RunPreflight
from acquisition.daemon.run_queue import REMOVED, RunQueue
from acquisition.daemon.run_thread import RunContext, RunThread, discard_raw
from acquisition.daemon.settings import DaemonSettings
from drivers.camera import RawFrame
from drivers.contracts.rig import Rig
from drivers.contracts.runfile import marked_open_for_write
from drivers.errors import DeviceError

log = logging.getLogger("mirrorgonio.runner")

__all__ = ["REMOVED", "RunConflictError", "RunEngine", "RunEngineError"]


class RunEngine:
    """Runs acquisitions on one rig's devices, recording them in the catalog.

    It owns the queue of runs (:attr:`queue`) and the thread of the run in progress; the frame
    the preview shows is kept here for a run's and a test shot's alike.
    """

    def __init__(
        self,
        settings: DaemonSettings,
        rig: Rig,
        devices: Devices,
        catalog: Catalog,
        *,
        wall_clock: Callable[[], float] = time.time,
        monotonic: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ):
        self.settings = settings
        self.rig = rig
        self.devices = devices
        self.catalog = catalog
        self.events = ProgressEvents()
        self.pending = PendingEnds(catalog)  # runs' ends the catalog could not record yet
        self.preflight = RunPreflight(settings, rig, devices)
        self.latest_frame: RawFrame | None = None
        self.latest_frame_run: str | None = None
        self.frame_serial = 0  # counts the frames shown: what the previews are cached by
        self._lock = threading.Lock()
        self.queue = RunQueue(catalog, self.preflight, self.events, self.pending, self._lock, start=self._run_now)
        self._context = RunContext(
            settings=settings,
            devices=devices,
            catalog=catalog,
            pending=self.pending,
            events=self.events,
            preflight=self.preflight,
            lock=self._lock,
            show_frame=self.show_frame,
            ended=self.queue.after_run,
            wall=wall_clock,
            mono=monotonic,
            sleep=sleep,
        )
        self._run: RunThread | None = None  # the latest run's thread
        self._manual: str | None = None  # what holds the devices outside a run (a test shot, a jog)
        self._stop_serial = itertools.count(1)
        Path(settings.runs_dir).mkdir(parents=True, exist_ok=True)

    # --- control ---------------------------------------------------------------------------
    # Every request that changes a run's state takes ``_lock``, and so does the run thread where
    # it decides to end: a request either applies to the run (and the run obeys it) or gets a
    # RunConflictError saying why not (409). The run thread holds the lock only for catalog
    # writes, never while a device works, so that a stop of the arm is never held up.
    @property
    def busy(self) -> bool:
        """A run's thread holds the rig: from its start until it records how its run ended.

        That record and this change under ``_lock`` together: a client that sees the run ended
        finds the engine free, and may start the next thing at once (the thread only exits).
        """
        return self._active() is not None

    def start_run(self, request: RunRequest) -> RunRecord:
        """Start a run of ``request``, or queue it behind the run in progress.

        It is ``running`` when this returns if the rig is free and no run waits in the queue;
        otherwise it is ``queued`` at the end of the queue, and starts by itself in its turn
        (``RunQueue.start_next``). Either way its schedule, its references and (unless ``force``)
        its estimated size against the free space are checked now.

        Raises
        ------
        RunConflictError
            The devices are held by a test shot, a jog or homing.
        RigError, RunEngineError, ClientFileError
            The request's schedule or references cannot be used (nothing is started or queued).
        InsufficientStorageError, StorageUnavailableError
            The run would not fit in the free space, or its directory cannot be written.
        """
        plan = self.preflight.plan(request)  # refuses unreadable references before anything starts
        with self._lock:
            self.pending.save()
            self._refuse_while_manual()
            if not request.force:
                self.preflight.check_room(plan, len(plan.tool_poses))
            waits = self._rig_taken() or bool(self.catalog.queued_runs())
            if not waits:
                self._require_idle()
            runs_dir = Path(self.settings.runs_dir)
            record = self.catalog.create_run(
                preset=request.preset,
                path_for=lambda run_id: str(runs_dir / f"{run_id}.h5"),
                n_positions=len(plan.tool_poses),
                request=request.model_dump(mode="json"),
            )
            if waits:
                log.info("run %s queued (position %s): %s", record.id, record.queue_position, request.preset)
                self.events.publish()
                return record
            self.catalog.release_queue()  # the operator started the rig again
            record = self._run_now(record, plan)
        log.info("run %s started: %s, %d positions", record.id, request.preset, len(plan.tool_poses))
        self.events.publish()
        return record

    def resume(self, run_id: str, force: bool = False) -> RunRecord:
        """Continue a paused run, or restart an interrupted or failed one where it stopped
        (refused when what it has left to take does not fit in the free space, unless ``force``).

        A resumed run's ``last_error`` is cleared: it shows an error again only if one happens.
        Restarting an interrupted or failed run releases a held queue: the operator has dealt
        with the rig, and the queue goes on once this run completes.
        """
        with self._lock:
            self.pending.save()
            record = self._own_run(run_id, "resume it")
            run = self._active(run_id)
            if record.state == "paused" and run is not None:
                if run.finishing:
                    raise RunConflictError(f"run {run_id} is ending")
                record = self.catalog.transition_run(run_id, "running")
                run.control.pause.clear()
                run.wake()
                self.events.publish()
                return record
            if record.state not in ("interrupted", "failed", "paused"):
                raise RunConflictError(
                    f"run {run_id} is {record.state}: only a paused, interrupted or failed run can resume"
                )
            self._require_idle(run_id)
            plan = self.preflight.plan(self._stored_request(record), with_references=False)
            if not force:
                path = self._run_file(record)
                salvage = path.stat().st_size if marked_open_for_write(path) else 0
                self.preflight.check_room(plan, record.n_positions - record.positions_done, salvage)
            if record.state == "failed":
                # The technician has cleared the fault: acknowledge the controller's alarm.
                self.devices.arm.reset_alarm()
            # Running as soon as the request returns: a client polling right after must
            # not see the old failed or interrupted state.
            record = self.catalog.transition_run(run_id, "running")
            self.catalog.release_queue()
            self.events.publish()
            self._launch(record, plan, resume=True)
            return record

    def _own_run(self, run_id: str, wanted: str) -> RunRecord:
        """The run, if it is this rig's; another rig's (a shared catalog) is refused before any
        device or file of this rig is looked at."""
        record = self.catalog.get_run(run_id)
        if record.rig != self.catalog.rig:
            raise OtherRigError(run_id, record.rig, self.catalog.rig, wanted)
        return record

    def pause(self, run_id: str) -> RunRecord:
        """Pause a running run between frames.

        Raises
        ------
        RunConflictError
            The run is not running (already paused, ended, or taking no more frames).
        """
        with self._lock:
            self._own_run(run_id, "pause it")
            record, run = self._require_current(run_id)
            if record.state != "running":
                raise RunConflictError(f"run {run_id} is {record.state}: only a running run can pause")
            record = self.catalog.transition_run(run_id, "paused")
            run.control.pause.set()
            run.wake()
            self.events.publish()
            return record

    def abort(self, run_id: str) -> RunRecord:
        """End a run in progress (or an interrupted one) as ``aborted``, keeping every frame taken;
        a queued run is taken out of the queue (:meth:`remove_queued`).

        Raises
        ------
        RunConflictError
            The run is neither in progress, queued nor interrupted, or is already ending.
        """
        with self._lock:
            self.pending.save()
            record = self._own_run(run_id, "abort it")
            if record.state == "queued":
                record = self.catalog.remove_from_queue(run_id, REMOVED)
                self.events.publish()
                return record
            if record.state == "interrupted" and self._active(run_id) is None:
                record = self.catalog.transition_run(run_id, "aborted", error="aborted by the operator")
                self.events.publish()
                return record
            _, run = self._require_current(run_id)
            run.control.abort.set()
            run.wake()
        try:
            self.devices.arm.stop()
        except DeviceError as exc:  # the run thread tries again, and records it if that fails too
            log.warning("abort of run %s: stopping the arm failed: %s", run_id, exc)
        run.join(timeout=60)
        return self.catalog.get_run(run_id)

    def stop_arm(self) -> None:
        """Stop the arm at once; a run in progress pauses and re-takes its position on resume.

        The run's pause is set before the arm is told to stop, so that the run thread takes no
        further step; the run is ``paused`` in the catalog when this returns (``last_error``
        saying where it stopped, unless it was paused already), or it was ending anyway.
        """
        run = self._active()
        if run is not None:
            run.control.stop = next(self._stop_serial)
            run.control.pause.set()
        try:
            self.devices.arm.stop()
        finally:
            if run is not None:
                self._pause_for_stop(run)

    @contextmanager
    def manual(self, what: str) -> Iterator[None]:
        """Hold the devices for ``what`` (a test shot, a jog, homing) outside a run: refused
        (RunConflictError) while a run is active or another such action lasts; a run is refused
        while it lasts."""
        with self._lock:
            self._require_idle()
            self._manual = what
        try:
            yield
        finally:
            self._manual = None

    def wait(self, timeout: float | None = None) -> None:
        """Wait for the latest run's thread to finish (tests, shutdown)."""
        run = self._run
        if run is not None:
            run.join(timeout)

    def shutdown(self) -> None:
        """Abort the run in progress (the queue is held: no queued run starts) and wait for it."""
        with self._lock:  # a run ending now has started the next one already, or starts none
            self.queue.closing = True
        run = self._run
        if run is not None and run.alive:
            run.control.abort.set()
            run.wake()
            run.join(timeout=30)

    def step(self, run_id: str) -> str | None:
        """What run ``run_id`` is doing now (``RunStatus.step``); None unless it is in progress."""
        run = self._active(run_id)
        return run.step if run is not None else None

    # --- the queue (RunQueue's, with the engine's refusals) --------------------------------
    def start_queue(self) -> RunRecord | None:
        """Release the queue's hold; start its next run now if the rig is free
        (``RunQueue.release``; RunConflictError while a test shot, a jog or homing lasts)."""
        with self._lock:
            self.pending.save()
            self._refuse_while_manual()
            return self.queue.release(rig_taken=self._rig_taken())

    def reorder_queue(self, run_ids: list[str]) -> list[RunRecord]:
        """The queued runs ``run_ids`` first, in that order (``RunQueue.reorder``)."""
        return self.queue.reorder(run_ids)

    def remove_queued(self, run_id: str) -> RunRecord:
        """Take a queued run out of the queue (``RunQueue.remove``)."""
        return self.queue.remove(run_id)

    def after_restart(self, interrupted: list[str]) -> None:
        """At daemon start: the queued runs wait for the operator (``RunQueue.after_restart``)."""
        self.queue.after_restart(interrupted)

    # --- the frame the preview shows -------------------------------------------------------
    def show_frame(self, run_id: str | None, frame: RawFrame) -> None:
        """The frame the preview shows (of run ``run_id``; None: a test shot)."""
        self.latest_frame, self.latest_frame_run = frame, run_id
        self.frame_serial += 1

    def discard_raw(self, frame: RawFrame) -> None:
        """Delete ``frame``'s raw file once decoded, unless the settings keep raw files."""
        discard_raw(frame, self.settings.camera.keep_raw_files)

    # --- internals -------------------------------------------------------------------------
    def _active(self, run_id: str | None = None) -> RunThread | None:
        """The run thread that holds the rig (that of run ``run_id``, if given), or None."""
        run = self._run
        if run is None or not run.holds_rig or run_id not in (None, run.run_id):
            return None
        return run

    def _rig_taken(self) -> bool:
        """A run is in progress, or its thread has not yet recorded how it ended (under ``_lock``)."""
        return self.catalog.active_run() is not None or self.busy

    def _refuse_while_manual(self) -> None:
        if self._manual is not None:
            raise RunConflictError(f"the devices are busy: {self._manual}")

    def _require_current(self, run_id: str) -> tuple[RunRecord, RunThread]:
        """The run and its thread, if at work and not yet ending (under ``_lock``)."""
        record = self.catalog.get_run(run_id)
        run = self._active(run_id)
        if run is None:
            raise RunConflictError(f"run {run_id} is {record.state}, not in progress")
        if run.finishing:
            raise RunConflictError(f"run {run_id} is ending: it takes no more frames")
        return record, run

    def _require_idle(self, run_id: str | None = None) -> None:
        """Refuse unless no run other than ``run_id`` is active and no run thread holds the rig
        (under ``_lock``)."""
        self._refuse_while_manual()
        active = self.catalog.active_run()
        if active is not None and active.id != run_id:
            raise RunConflictError(f"run {active.id} is already active on this rig")
        run = self._active()
        if run is not None:
            raise RunConflictError(f"run {run.run_id} is still ending on this rig")

    @staticmethod
    def _run_file(record: RunRecord) -> Path:
        """Where run ``record``'s file is (the catalog names it as the run is created)."""
        if record.path is None:
            raise RunConflictError(f"run {record.id} has no run file")
        return Path(record.path)

    @staticmethod
    def _stored_request(record: RunRecord) -> RunRequest:
        """The request a run was started with, as the catalog keeps it."""
        try:
            return RunRequest.model_validate(record.request)
        except ValidationError as exc:  # stored by a version that checked less
            where = ".".join(str(part) for part in exc.errors()[0]["loc"])
            raise RunConflictError(
                f"run {record.id} cannot resume: its request's {where}: {exc.errors()[0]['msg']}"
            ) from None

    def _pause_for_stop(self, run: RunThread) -> None:
        """After a stop of the arm: ``run`` is paused in the catalog, unless it is ending (the
        stop does not concern it), was paused already, or was resumed since the stop set its
        pause (the later request stands)."""
        with self._lock:
            current = self._active(run.run_id) is run and not run.finishing
            if not current or not run.control.pause.is_set():
                return
            if self.catalog.get_run(run.run_id).state == "running":
                where = " before the first move" if run.position is None else f" at position {run.position}"
                self.catalog.transition_run(run.run_id, "paused", error=f"arm stopped by the operator{where}")
                log.warning("arm stopped by the operator%s; run %s paused", where, run.run_id)
            run.wake()
            self.events.publish()

    def _run_now(self, record: RunRecord, plan: RunPlan) -> RunRecord:
        """``record`` running, then its thread started with ``plan`` (running first: a pause
        right after the start applies to it). Under ``_lock``; the queue's way to start a run."""
        record = self.catalog.transition_run(record.id, "running")
        self._launch(record, plan, resume=False)
        return record

    def _launch(self, record: RunRecord, plan: RunPlan, resume: bool) -> None:
        self._run = RunThread(self._context, record.id, self._run_file(record), plan, resume)
        self._run.start()
