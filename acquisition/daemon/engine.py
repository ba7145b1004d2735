"""The run engine: moves the arm through a schedule and takes a bracket at each position.

One run in progress at a time per rig; the runs asked for meanwhile wait in a queue, in an
order the operator may change (``docs/daemon.md``, "The queue of runs"). States: queued →
running ⇄ paused → complete | aborted | failed, and interrupted for a run whose daemon died
(resumable, as is a failed run once its fault is cleared). Pause takes effect between frames;
abort stops the arm and keeps every frame taken; a transient device error is retried, a
persistent one fails the run with the device's own message. A run that completes starts the
next queued one; one that fails or is aborted holds the queue, with the reason, until a run
is resumed or the queue is started again.

A run takes calibration frames with the measured light off (``docs/daemon.md``): with the arm
at the first position, ambient frames (the room lit) and dark frames (the room dark), then the
light goes back on for the sweep; after the last position the same again when the request
asks for it. The light switch is a device; a manual one pauses the run with what the operator
must do, and the operator resumes it. A resumed run takes only the sets its file lacks.

Frames of position i are written by a writer thread while the arm already moves to
position i + 1, so the software's time hides behind the hardware's.
"""

from __future__ import annotations

import itertools
import logging
import os
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

from pydantic import ValidationError

from acquisition.daemon.bracketing import NoiseModel, exposures_from_metering, is_saturated
from acquisition.daemon.catalog import Catalog, RunRecord
from acquisition.daemon.catalog.pending import PendingEnds
from acquisition.daemon.devices import Devices
from acquisition.daemon.models import AutoBracket, FixedBracket, RunRequest
from acquisition.daemon.run_control import (
    Aborted,
    Control,
    OperatorStop,
    ProgressEvents,
    RunConflictError,
    RunEngineError,
)
from acquisition.daemon.run_plan import Arrival, RunPlan, WriteBehind, calibration_sets, calibration_shot
from acquisition.daemon.run_preflight import RunPreflight
from acquisition.daemon.run_queue import REMOVED, RunQueue
from acquisition.daemon.settings import DaemonSettings
from acquisition.daemon.storage import failure_message
from drivers.camera import RawFrame
from drivers.contracts.rig import Rig
from drivers.contracts.runfile import (
    PositionTimes,
    RunFileError,
    RunFileWriter,
    marked_open_for_write,
    storage_errno,
)
from drivers.errors import CommunicationError, DeviceError, DeviceTimeoutError, MoveInterruptedError
from drivers.light import SWEEP, Lighting

log = logging.getLogger("mirrorgonio.runner")

__all__ = ["RunConflictError", "RunEngine", "RunEngineError"]


class RunEngine(RunQueue):
    """Runs acquisitions on one rig's devices, recording them in the catalog."""

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
        self._wall = wall_clock
        self._mono = monotonic
        self._sleep = sleep
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._control = Control()
        self._current: str | None = None
        self.latest_frame: RawFrame | None = None
        self.latest_frame_run: str | None = None
        self.frame_serial = 0  # counts the frames shown: what the previews are cached by
        self._step: str | None = None
        self.pending = PendingEnds(catalog)  # runs' ends the catalog could not record yet
        self._finishing = False  # the run thread has taken its last frame (or failed): it is ending
        self._position: int | None = None  # the position the run thread is at, or moving to
        self._manual: str | None = None  # what holds the devices outside a run (a test shot, a jog)
        self._stop_serial = itertools.count(1)
        self._exiting = False  # the run thread has recorded its run's end: it no longer holds the rig
        self._closing = False  # the daemon shuts down: no queued run starts
        self.preflight = RunPreflight(settings, rig, devices)
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
        return self._thread is not None and self._thread.is_alive() and not self._exiting

    def start_run(self, request: RunRequest) -> RunRecord:
        """Start a run of ``request``, or queue it behind the run in progress.

        It is ``running`` when this returns if the rig is free and no run waits in the queue;
        otherwise it is ``queued`` at the end of the queue, and starts by itself in its turn
        (:meth:`_start_next`). Either way its schedule, its references and (unless ``force``)
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
        rig, tool, light = self.preflight.poses(request)
        references = self.preflight.references(rig, request)  # refuse unreadable references before anything starts
        with self._lock:
            self.pending.save()
            if self._manual is not None:
                raise RunConflictError(f"the devices are busy: {self._manual}")
            if not request.force:
                self.preflight.check_room(request, len(tool))
            waits = self._rig_taken() or bool(self.catalog.queued_runs())
            if not waits:
                self._require_idle()
            runs_dir = Path(self.settings.runs_dir)
            record = self.catalog.create_run(
                preset=request.preset,
                path_for=lambda run_id: str(runs_dir / f"{run_id}.h5"),
                n_positions=len(tool),
                request=request.model_dump(mode="json"),
            )
            if waits:
                log.info("run %s queued (position %s): %s", record.id, record.queue_position, request.preset)
                self.events.publish()
                return record
            self.catalog.release_queue()  # the operator started the rig again
            record = self._run_now(record, RunPlan(record.id, rig, tool, light, request, Path(record.path), references))
        log.info("run %s started: %s, %d positions", record.id, request.preset, len(tool))
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
            record = self.catalog.get_run(run_id)
            if record.state == "paused" and self.busy and self._current == run_id:
                if self._finishing:
                    raise RunConflictError(f"run {run_id} is ending")
                record = self.catalog.transition_run(run_id, "running")
                self._control.pause.clear()
                self._notify()
                self.events.publish()
                return record
            if record.state not in ("interrupted", "failed", "paused"):
                raise RunConflictError(
                    f"run {run_id} is {record.state}: only a paused, interrupted or failed run can resume"
                )
            self._require_idle(run_id)
            try:
                request = RunRequest.model_validate(record.request)
            except ValidationError as exc:  # stored by a version that checked less
                where = ".".join(str(part) for part in exc.errors()[0]["loc"])
                raise RunConflictError(
                    f"run {run_id} cannot resume: its request's {where}: {exc.errors()[0]['msg']}"
                ) from None
            rig, tool, light = self.preflight.poses(request)
            if not force:
                salvage = Path(record.path).stat().st_size if marked_open_for_write(record.path) else 0
                self.preflight.check_room(request, record.n_positions - record.positions_done, salvage)
            if record.state == "failed":
                # The technician has cleared the fault: acknowledge the controller's alarm.
                self.devices.arm.reset_alarm()
            plan = RunPlan(run_id, rig, tool, light, request, Path(record.path))
            # Running as soon as the request returns: a client polling right after must
            # not see the old failed or interrupted state.
            record = self.catalog.transition_run(run_id, "running")
            self.catalog.release_queue()
            self.events.publish()
            self._launch(plan, resume=True)
            return record

    def _rig_taken(self) -> bool:
        """A run is in progress, or its thread has not yet recorded how it ended (under ``_lock``)."""
        return self.catalog.active_run() is not None or self.busy

    def pause(self, run_id: str) -> RunRecord:
        """Pause a running run between frames.

        Raises
        ------
        RunConflictError
            The run is not running (already paused, ended, or taking no more frames).
        """
        with self._lock:
            record = self._require_current(run_id)
            if record.state != "running":
                raise RunConflictError(f"run {run_id} is {record.state}: only a running run can pause")
            record = self.catalog.transition_run(run_id, "paused")
            self._control.pause.set()
            self._notify()
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
            record = self.catalog.get_run(run_id)
            if record.state == "queued":
                record = self.catalog.remove_from_queue(run_id, REMOVED)
                self.events.publish()
                return record
            if record.state == "interrupted" and not (self.busy and self._current == run_id):
                record = self.catalog.transition_run(run_id, "aborted", error="aborted by the operator")
                self.events.publish()
                return record
            self._require_current(run_id)
            self._control.abort.set()
            self._notify()
            thread = self._thread
        try:
            self.devices.arm.stop()
        except DeviceError as exc:  # the run thread tries again, and records it if that fails too
            log.warning("abort of run %s: stopping the arm failed: %s", run_id, exc)
        if thread is not None:
            thread.join(timeout=60)
        return self.catalog.get_run(run_id)

    def stop_arm(self) -> None:
        """Stop the arm at once; a run in progress pauses and re-takes its position on resume.

        The run's pause is set before the arm is told to stop, so that the run thread takes no
        further step; the run is ``paused`` in the catalog when this returns (``last_error``
        saying where it stopped, unless it was paused already), or it was ending anyway.
        """
        control = self._control
        in_progress = self.busy
        if in_progress:
            control.stop = next(self._stop_serial)
            control.pause.set()
        try:
            self.devices.arm.stop()
        finally:
            if in_progress:
                self._pause_for_stop(control)

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
        """Wait for the current run's thread to finish (tests, shutdown)."""
        thread = self._thread
        if thread is not None:
            thread.join(timeout)

    def shutdown(self) -> None:
        """Abort the run in progress (the queue is held: no queued run starts) and wait for it."""
        with self._lock:  # a run ending now has started the next one already, or starts none
            self._closing = True
        thread = self._thread
        if thread is not None and thread.is_alive():
            self._control.abort.set()
            self._notify()
            thread.join(timeout=30)

    def step(self, run_id: str) -> str | None:
        """What run ``run_id`` is doing now (``RunStatus.step``); None unless it is in progress."""
        return self._step if run_id == self._current and self.busy else None

    # --- internals -------------------------------------------------------------------------
    def _require_current(self, run_id: str) -> RunRecord:
        """The run, if its thread is at work and not yet ending (under ``_lock``)."""
        record = self.catalog.get_run(run_id)
        if not (self.busy and self._current == run_id):
            raise RunConflictError(f"run {run_id} is {record.state}, not in progress")
        if self._finishing:
            raise RunConflictError(f"run {run_id} is ending: it takes no more frames")
        return record

    def _require_idle(self, run_id: str | None = None) -> None:
        """Refuse unless no run other than ``run_id`` is active and no run thread holds the rig
        (under ``_lock``)."""
        if self._manual is not None:
            raise RunConflictError(f"the devices are busy: {self._manual}")
        active = self.catalog.active_run()
        if active is not None and active.id != run_id:
            raise RunConflictError(f"run {active.id} is already active on this rig")
        if self.busy:
            raise RunConflictError(f"run {self._current or 'the previous run'} is still ending on this rig")

    def _pause_for_stop(self, control: Control) -> None:
        """After a stop of the arm: the run of ``control`` is paused in the catalog, unless it
        is ending (the stop does not concern it), was paused already, or was resumed since the
        stop set its pause (the later request stands)."""
        with self._lock:
            run_id = self._current
            current = control is self._control and self.busy and not self._finishing
            if not current or run_id is None or not control.pause.is_set():
                return
            if self.catalog.get_run(run_id).state == "running":
                where = " before the first move" if self._position is None else f" at position {self._position}"
                self.catalog.transition_run(run_id, "paused", error=f"arm stopped by the operator{where}")
                log.warning("arm stopped by the operator%s; run %s paused", where, run_id)
            self._notify()
            self.events.publish()

    def _notify(self) -> None:
        with self._control.wake:
            self._control.wake.notify_all()

    def _launch(self, plan: RunPlan, resume: bool) -> None:
        self._control = Control()
        self._current = plan.run_id
        self._finishing = False
        self._exiting = False
        self._position = None
        self._thread = threading.Thread(
            target=self._execute, args=(plan, resume), name=f"run-{plan.run_id}", daemon=True
        )
        self._thread.start()

    def _checkpoint(self) -> None:
        """Between frames: honour abort, and wait while paused."""
        control = self._control
        with control.wake:
            while control.pause.is_set() and not control.abort.is_set():
                control.wake.wait(timeout=0.5)
        if control.abort.is_set():
            raise Aborted()

    def _finish(self) -> None:
        """After the last frame: honour a pause or an abort that came in meanwhile, then mark
        the run ending, so that from here on a pause, a resume or an abort is refused (409)
        and a stop of the arm leaves it alone."""
        while True:
            self._checkpoint()
            with self._lock:
                if not self._control.pause.is_set():
                    self._finishing = True
                    return

    def _device(self, what: str, action: Callable, *args, **kwargs):
        """Run a device action, retrying transient errors."""
        control = self._control
        attempts = self.settings.device_retries + 1
        for attempt in range(attempts):
            stop = control.stop
            try:
                return action(*args, **kwargs)
            except MoveInterruptedError:
                if control.abort.is_set():
                    raise Aborted() from None
                if control.stop != stop:
                    raise OperatorStop() from None
                raise
            except (CommunicationError, DeviceTimeoutError) as exc:
                if attempt == attempts - 1 or control.abort.is_set():
                    raise
                log.warning("%s failed (%s); retry %d of %d", what, exc, attempt + 1, attempts - 1)
                self._sleep(0.2 * (attempt + 1))
        raise AssertionError("unreachable")

    def _bracket(self, bracket: FixedBracket | AutoBracket) -> list[float]:
        if isinstance(bracket, FixedBracket):
            return list(bracket.exposures_s)
        rule = self.settings.auto_bracket.model_copy(update=bracket.overrides())
        noise = NoiseModel(self.rig.camera.gain_e_per_dn, self.rig.camera.read_noise_e)
        exposure = rule.metering_exposure_s
        for _ in range(8):
            self._checkpoint()
            meter = self._device("metering capture", self.devices.camera.capture, exposure)
            self.discard_raw(meter)
            if not is_saturated(meter) or exposure <= rule.min_exposure_s:
                return exposures_from_metering(meter, rule, noise)
            exposure = max(exposure / 8.0, rule.min_exposure_s)
        return exposures_from_metering(meter, rule, noise)

    def discard_raw(self, frame: RawFrame) -> None:
        if not self.settings.camera.keep_raw_files and frame.source:
            try:
                os.unlink(frame.source)
            except OSError:
                pass

    def _execute(self, plan: RunPlan, resume: bool) -> None:
        """The run thread: open the run file, take every incomplete position, record how it ended."""
        writer: RunFileWriter | None = None
        behind = WriteBehind()
        outcome, message = "complete", ""
        try:
            writer = self._open_run_file(plan, resume)
            behind.thread = threading.Thread(
                target=self._write_loop, args=(plan.run_id, writer, behind), name=f"write-{plan.run_id}", daemon=True
            )
            behind.thread.start()
            self._take_positions(plan, writer, behind)
        except Aborted:
            outcome, message = "aborted", "aborted by the operator"
        except DeviceError as exc:
            outcome, message = "failed", str(exc)
        except Exception as exc:  # noqa: BLE001 - any other failure still keeps the data
            outcome, message = "failed", failure_message(exc, plan.path)
            if storage_errno(exc) is None:
                log.exception("run %s failed", plan.run_id)
        finally:
            self._end_run(plan.run_id, outcome, message, writer, behind)

    def _open_run_file(self, plan: RunPlan, resume: bool) -> RunFileWriter:
        """The run file, created or reopened, with the run marked running in it (the catalog
        says so already: :meth:`start_run`, :meth:`resume`)."""
        if resume and plan.path.exists():  # a run that failed creating it resumes by creating it
            writer = RunFileWriter.reopen(plan.path)
        else:
            writer = RunFileWriter.create(plan.path, self.preflight.header(plan))
        writer.set_status("running")
        self.events.publish()
        return writer

    def _take_positions(self, plan: RunPlan, writer: RunFileWriter, behind: WriteBehind) -> None:
        """The calibration frames before the sweep, every position the run file does not hold
        complete, in order, until the last is written, then the calibration frames after it.

        The calibration frames before are taken at the first position to take, and that
        position's frames follow without another move; those after, at the last position.
        """
        index = writer.first_incomplete()
        arrival = self._calibrate(plan, writer, "before", 0 if index is None else index)
        if index is not None:
            self._ready_for_sweep(plan.run_id, bool(calibration_sets(writer.header.calibration)))
        while index is not None and index < len(plan.tool_poses):
            if writer.complete[index]:
                index += 1
                continue
            try:
                arrival = self._take_position(
                    plan, index, behind, arrival if arrival and arrival.index == index else None
                )
            except OperatorStop:
                arrival = None
                continue  # re-take this position once resumed
            if behind.errors:
                raise behind.errors[0]
            index += 1
        behind.queue.join()
        if behind.errors:
            raise behind.errors[0]
        last = len(plan.tool_poses) - 1
        self._calibrate(plan, writer, "after", last, arrival if arrival and arrival.index == last else None)
        self._finish()

    def _move(self, plan: RunPlan, index: int) -> Arrival:
        """Move the arm to position ``index`` (unless paused or aborted just now)."""
        self._position = index
        self._checkpoint()
        move_started = self._wall()
        measured = self._device(
            "move", self.devices.arm.move_to, plan.tool_poses[index], timeout=self.settings.arm.move_timeout_s
        )
        return Arrival(index, measured, move_started, self._wall())

    # --- calibration frames ----------------------------------------------------------------
    def _calibrate(
        self, plan: RunPlan, writer: RunFileWriter, when: str, index: int, arrival: Arrival | None = None
    ) -> Arrival | None:
        """Take the run's calibration sets of ``when`` (``before`` or ``after`` the sweep) that the
        run file does not hold complete, with the arm at position ``index`` (moved there unless
        ``arrival`` says it is). Returns the arm's arrival there, if it moved or was there."""
        calibration = writer.header.calibration
        pending = [role for role, at in calibration_sets(calibration) if at == when]
        pending = [role for role in pending if not writer.calibration_complete(role, when)]
        if not pending:
            return arrival
        if not self.devices.light.takes_calibration:
            log.warning("run %s: no light switch: the calibration frames %s the sweep are not taken", plan.run_id, when)
            return arrival
        for role in pending:
            lighting, exposures = calibration_shot(calibration, role)
            while True:
                try:
                    self._checkpoint()
                    if arrival is None:
                        self._set_step(f"calibration: moving to position {index + 1} for the frames {when} the sweep")
                        arrival = self._move(plan, index)
                    frames = self._calibration_frames(plan.run_id, (role, when), lighting, exposures)
                    break
                except OperatorStop:
                    arrival = None  # taken again once resumed
            writer.write_calibration(role, when, frames)
            for frame in frames:
                self.discard_raw(frame)
        return arrival

    def _calibration_frames(
        self, run_id: str, which: tuple[str, str], lighting: Lighting, exposures: list[float]
    ) -> list[RawFrame]:
        """One calibration set's frames, the lights in ``lighting``."""
        role, when = which
        self._switch(run_id, lighting)
        frames: list[RawFrame] = []
        for k, exposure in enumerate(exposures):
            self._checkpoint()
            self._set_step(
                f"calibration: {role} frames {when} the sweep ({lighting.describe()}), "
                f"frame {k + 1} of {len(exposures)}"
            )
            frame = self._device("calibration capture", self.devices.camera.capture, exposure)
            frames.append(frame)
            self.show_frame(run_id, frame)
        return frames

    def _ready_for_sweep(self, run_id: str, calibrates: bool) -> None:
        """The light on and the room dark before the sweep: after calibration frames, or whenever
        the switch left them otherwise. A switch whose state is unknown (a manual one when the
        daemon has just started) is left alone unless the run takes calibration frames."""
        switch = self.devices.light
        if switch.takes_calibration and switch.state != SWEEP and (switch.state is not None or calibrates):
            self._switch(run_id, SWEEP)

    def _switch(self, run_id: str, lighting: Lighting) -> None:
        """Put the lights in ``lighting``: at once, or once the operator has done it and resumed."""
        switch = self.devices.light
        if switch.state == lighting:
            return
        instruction = switch.instruction(lighting)
        if instruction is not None:
            self._wait_for_operator(run_id, instruction)
        self._device("light switch", switch.set, lighting)

    def _wait_for_operator(self, run_id: str, instruction: str) -> None:
        """Pause the run, saying what the operator must do; return when it is resumed."""
        log.info("run %s paused for the operator: %s", run_id, instruction)
        with self._lock:
            if self.catalog.get_run(run_id).state != "paused":
                self.catalog.transition_run(run_id, "paused")
            self._control.pause.set()
        self._set_step(f"waiting for the operator: {instruction}")
        self._checkpoint()

    def _set_step(self, step: str) -> None:
        self._step = step
        self.events.publish()

    def show_frame(self, run_id: str | None, frame: RawFrame) -> None:
        """The frame the preview shows (of run ``run_id``; None: a test shot)."""
        self.latest_frame, self.latest_frame_run = frame, run_id
        self.frame_serial += 1

    def _write_loop(self, run_id: str, writer: RunFileWriter, behind: WriteBehind) -> None:
        """The writer thread: write each position handed over, and record the run's progress.

        A failed write is kept for the run thread to raise; the positions queued after it are
        dropped. ``None`` ends the loop.
        """
        while True:
            item = behind.queue.get()
            try:
                if item is None:
                    return
                index, measured, times, frames = item
                if behind.errors:
                    continue
                try:
                    writer.write_position(index, measured, times, frames)
                    for frame in frames:
                        self.discard_raw(frame)
                    recent = behind.durations[-10:]
                    self.catalog.update_progress(
                        run_id,
                        positions_done=int(writer.complete.sum()),
                        current_position=index if self._position is None else self._position,  # where the arm is
                        seconds_per_position=sum(recent) / len(recent) if behind.durations else None,
                        exposures_per_position=len(frames),
                    )
                except BaseException as exc:  # noqa: BLE001 - reported to the run thread
                    behind.errors.append(exc)
                    continue
                self.events.publish()
            finally:
                behind.queue.task_done()

    def _end_run(
        self, run_id: str, outcome: str, message: str, writer: RunFileWriter | None, behind: WriteBehind
    ) -> None:
        """However the run ended: stop the arm unless it completed, write the frames already
        taken, and record the outcome in the run file and the catalog."""
        with self._lock:
            self._finishing = True  # a pause, resume or abort no longer applies (409)
        if outcome != "complete":
            try:
                self.devices.arm.stop()
            except DeviceError as exc:
                message += f"; stopping the arm also failed: {exc}"
        if behind.thread is not None and behind.thread.is_alive():
            behind.queue.put(None)  # frames already taken are still written
            behind.thread.join()
        if behind.errors and outcome == "complete":
            outcome, message = "failed", failure_message(behind.errors[0], None)
        if writer is not None:
            outcome, message = self._close_run_file(writer, outcome, message)
        with self._lock:  # a request sees the run in progress, or ended with the queue moved on
            self.pending.record(run_id, outcome, message)
            level = logging.INFO if outcome == "complete" else logging.WARNING
            log.log(level, "run %s %s%s", run_id, outcome, f": {message}" if message else "")
            self._current = None if outcome != "paused" else run_id
            self._step = None
            self._exiting = True
            self._queue_after(run_id, outcome, message)
        self.events.publish()

    def _close_run_file(self, writer: RunFileWriter, outcome: str, message: str) -> tuple[str, str]:
        """Record the outcome in the run file and close it: the outcome and its message, a
        write failure's when the file refused them (a run that took every position but could
        not record that fails, and resumes to complete)."""
        try:
            writer.set_status(outcome, message)
        except RunFileError as exc:
            log.warning("run file %s: %s", writer.path, exc)
        try:
            writer.close()
        except RunFileError as exc:
            log.warning("run file %s: %s", writer.path, exc)
        if writer.failed is not None and outcome != "aborted":
            return "failed", str(writer.failed)
        return outcome, message

    def _take_position(self, plan: RunPlan, index: int, behind: WriteBehind, arrival: Arrival | None = None) -> Arrival:
        """Move to position ``index`` (unless ``arrival`` says the arm is there), take its bracket
        and hand it to the writer thread."""
        started = self._mono()
        self._checkpoint()
        self._position = index
        # The position count is the writer thread's alone: a count read here could be stale by the
        # time it is written, and put a position it just wrote back to undone.
        self.catalog.update_progress(plan.run_id, current_position=index)
        self._set_step(f"sweep, position {index + 1} of {len(plan.tool_poses)}")
        if arrival is None:
            arrival = self._move(plan, index)
        exposures = self._bracket(plan.request.bracket)
        frames: list[RawFrame] = []
        for exposure in exposures:
            self._checkpoint()
            frame = self._device("capture", self.devices.camera.capture, exposure)
            frames.append(frame)
            self.show_frame(plan.run_id, frame)
        times = PositionTimes(arrival.move_started, arrival.in_position, self._wall())
        behind.durations.append(self._mono() - started)
        # Blocks only while the previous position is still being written.
        behind.queue.put((index, arrival.measured, times, frames))
        return arrival
