"""One run's thread, as the run engine (``acquisition.daemon.engine``) starts it: it moves the
arm through the run's schedule, takes a bracket at each position and the run's calibration
frames, and records how the run ended.

Between frames it obeys the requests (:class:`~acquisition.daemon.run_control.Control`): a pause
waits, an abort ends the run keeping every frame taken, a stop of the arm re-takes the position
once resumed. A transient device error is retried; a persistent one fails the run with the
device's own message.

Calibration frames (``docs/daemon.md``): with the arm at the first position, ambient frames
(the room lit) and dark frames (the room dark), then the light goes back on for the sweep;
after the last position the same again when the request asks for it. A manual light switch
pauses the run with what the operator must do, and the operator resumes it. A resumed run
takes only the sets its file lacks.

Frames of position i are written by a writer thread while the arm already moves to
position i + 1, so the software's time hides behind the hardware's.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from acquisition.daemon.bracketing import NoiseModel, exposures_from_metering, is_saturated
from acquisition.daemon.catalog import Catalog
from acquisition.daemon.catalog.pending import PendingEnds
from acquisition.daemon.devices import Devices
from acquisition.daemon.models import FixedBracket
from acquisition.daemon.run_control import Aborted, Control, OperatorStop, ProgressEvents
from acquisition.daemon.run_plan import Arrival, RunPlan, WriteBehind, calibration_sets, calibration_shot
from acquisition.daemon.run_preflight import RunPreflight
from acquisition.daemon.settings import DaemonSettings
from acquisition.daemon.storage import failure_message
from drivers.camera import RawFrame
from drivers.contracts.runfile import PositionTimes, RunFileError, RunFileWriter, storage_errno
from drivers.errors import CommunicationError, DeviceError, DeviceTimeoutError, MoveInterruptedError
from drivers.light import SWEEP, Lighting

log = logging.getLogger("mirrorgonio.runner")


def discard_raw(frame: RawFrame, keep_raw_files: bool) -> None:
    """Delete the camera's raw file of ``frame`` once it is decoded, unless raw files are kept."""
    if not keep_raw_files and frame.source:
        try:
            os.unlink(frame.source)
        except OSError:
            pass


@dataclass(frozen=True)
class RunContext:
    """What a run's thread uses of the daemon around it (the engine's, shared by its runs)."""

    settings: DaemonSettings
    devices: Devices
    catalog: Catalog
    pending: PendingEnds  # the runs' ends the catalog could not record yet
    events: ProgressEvents
    preflight: RunPreflight  # the header of a run file created as the run starts
    lock: threading.Lock  # the engine's: a request and the run's own decisions take it in turn
    show_frame: Callable[[str | None, RawFrame], None]  # the frame the preview shows
    ended: Callable[[str, str, str], None]  # after the run's end is recorded, under ``lock``
    wall: Callable[[], float] = time.time
    mono: Callable[[], float] = time.monotonic
    sleep: Callable[[float], None] = time.sleep


class RunThread:
    """The thread of run ``run_id``, taking ``plan`` into the run file at ``path`` (reopened
    when ``resume``), and what the engine's requests read and set of it.

    ``control`` is what the requests set and the thread obeys; ``step`` says what the thread is
    doing; ``position`` is where the arm is or is going; ``finishing``: the run takes no more
    frames (a pause, a resume or an abort no longer applies); ``exiting``: the run's end is
    recorded and the thread no longer holds the rig. Each changes under the context's lock
    where a request decides on it.
    """

    def __init__(self, context: RunContext, run_id: str, path: Path, plan: RunPlan, resume: bool):
        self.context = context
        self.run_id = run_id
        self.path = path
        self.plan = plan
        self.resume = resume
        self.control = Control()
        self.step: str | None = None
        self.position: int | None = None
        self.finishing = False
        self.exiting = False
        self._thread = threading.Thread(target=self._execute, name=f"run-{run_id}", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def join(self, timeout: float | None = None) -> None:
        self._thread.join(timeout)

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    @property
    def holds_rig(self) -> bool:
        """The thread is at work: started, and its run's end not yet recorded."""
        return self._thread.is_alive() and not self.exiting

    def wake(self) -> None:
        """Wake the thread where it waits while paused, to read its control again."""
        with self.control.wake:
            self.control.wake.notify_all()

    # --- the run's life --------------------------------------------------------------------
    def _execute(self) -> None:
        """The run thread: open the run file, take every incomplete position, record how it ended."""
        writer: RunFileWriter | None = None
        behind = WriteBehind()
        outcome, message = "complete", ""
        try:
            writer = self._open_run_file()
            behind.thread = threading.Thread(
                target=self._write_loop, args=(writer, behind), name=f"write-{self.run_id}", daemon=True
            )
            behind.thread.start()
            self._take_positions(writer, behind)
        except Aborted:
            outcome, message = "aborted", "aborted by the operator"
        except DeviceError as exc:
            outcome, message = "failed", str(exc)
        except Exception as exc:  # noqa: BLE001 - any other failure still keeps the data
            outcome, message = "failed", failure_message(exc, self.path)
            if storage_errno(exc) is None:
                log.exception("run %s failed", self.run_id)
        finally:
            self._end_run(outcome, message, writer, behind)

    def _open_run_file(self) -> RunFileWriter:
        """The run file, created or reopened, with the run marked running in it (the catalog
        says so already: ``RunEngine.start_run``, ``RunEngine.resume``)."""
        if self.resume and self.path.exists():  # a run that failed creating it resumes by creating it
            writer = RunFileWriter.reopen(self.path)
        else:
            writer = RunFileWriter.create(self.path, self.context.preflight.header(self.run_id, self.plan))
        writer.set_status("running")
        self.context.events.publish()
        return writer

    def _take_positions(self, writer: RunFileWriter, behind: WriteBehind) -> None:
        """The calibration frames before the sweep, every position the run file does not hold
        complete, in order, until the last is written, then the calibration frames after it.

        The calibration frames before are taken at the first position to take, and that
        position's frames follow without another move; those after, at the last position.
        """
        positions = len(self.plan.tool_poses)
        index = writer.first_incomplete()
        arrival = self._calibrate(writer, "before", 0 if index is None else index)
        if index is not None:
            self._ready_for_sweep(bool(calibration_sets(writer.header.calibration)))
        while index is not None and index < positions:
            if writer.complete[index]:
                index += 1
                continue
            try:
                arrival = self._take_position(index, behind, arrival if arrival and arrival.index == index else None)
            except OperatorStop:
                arrival = None
                continue  # re-take this position once resumed
            if behind.errors:
                raise behind.errors[0]
            index += 1
        behind.queue.join()
        if behind.errors:
            raise behind.errors[0]
        last = positions - 1
        self._calibrate(writer, "after", last, arrival if arrival and arrival.index == last else None)
        self._finish()

    def _take_position(self, index: int, behind: WriteBehind, arrival: Arrival | None = None) -> Arrival:
        """Move to position ``index`` (unless ``arrival`` says the arm is there), take its bracket
        and hand it to the writer thread."""
        context = self.context
        started = context.mono()
        self._checkpoint()
        self.position = index
        # The position count is the writer thread's alone: a count read here could be stale by the
        # time it is written, and put a position it just wrote back to undone.
        context.catalog.update_progress(self.run_id, current_position=index)
        self._set_step(f"sweep, position {index + 1} of {len(self.plan.tool_poses)}")
        if arrival is None:
            arrival = self._move(index)
        frames: list[RawFrame] = []
        for exposure in self._bracket():
            self._checkpoint()
            frame = self._device("capture", context.devices.camera.capture, exposure)
            frames.append(frame)
            context.show_frame(self.run_id, frame)
        times = PositionTimes(arrival.move_started, arrival.in_position, context.wall())
        behind.durations.append(context.mono() - started)
        # Blocks only while the previous position is still being written.
        behind.queue.put((index, arrival.measured, times, frames))
        return arrival

    def _move(self, index: int) -> Arrival:
        """Move the arm to position ``index`` (unless paused or aborted just now)."""
        context = self.context
        self.position = index
        self._checkpoint()
        move_started = context.wall()
        pose = self.plan.tool_poses[index]
        measured = self._device("move", context.devices.arm.move_to, pose, timeout=context.settings.arm.move_timeout_s)
        return Arrival(index, measured, move_started, context.wall())

    def _bracket(self) -> list[float]:
        """The exposures of the position the arm is at: the fixed bracket, or the auto rule's
        from a metering frame (metered again, shorter, while it is saturated)."""
        bracket, rule = self.plan.request.bracket, self.plan.auto_bracket
        if isinstance(bracket, FixedBracket):
            return list(bracket.exposures_s)
        assert rule is not None  # a plan carries its auto bracket's rule (RunPlan)
        camera = self.plan.rig.camera
        noise = NoiseModel(camera.gain_e_per_dn, camera.read_noise_e)
        exposure = rule.metering_exposure_s
        for _ in range(8):
            self._checkpoint()
            meter = self._device("metering capture", self.context.devices.camera.capture, exposure)
            self._discard(meter)
            if not is_saturated(meter) or exposure <= rule.min_exposure_s:
                return exposures_from_metering(meter, rule, noise)
            exposure = max(exposure / 8.0, rule.min_exposure_s)
        return exposures_from_metering(meter, rule, noise)

    # --- calibration frames ----------------------------------------------------------------
    def _calibrate(
        self, writer: RunFileWriter, when: str, index: int, arrival: Arrival | None = None
    ) -> Arrival | None:
        """Take the run's calibration sets of ``when`` (``before`` or ``after`` the sweep) that the
        run file does not hold complete, with the arm at position ``index`` (moved there unless
        ``arrival`` says it is). Returns the arm's arrival there, if it moved or was there."""
        calibration = writer.header.calibration
        pending = [role for role, at in calibration_sets(calibration) if at == when]
        pending = [role for role in pending if not writer.calibration_complete(role, when)]
        if not pending:
            return arrival
        if not self.context.devices.light.takes_calibration:
            log.warning("run %s: no light switch: the calibration frames %s the sweep are not taken", self.run_id, when)
            return arrival
        for role in pending:
            lighting, exposures = calibration_shot(calibration, role)
            while True:
                try:
                    self._checkpoint()
                    if arrival is None:
                        self._set_step(f"calibration: moving to position {index + 1} for the frames {when} the sweep")
                        arrival = self._move(index)
                    frames = self._calibration_frames((role, when), lighting, exposures)
                    break
                except OperatorStop:
                    arrival = None  # taken again once resumed
            writer.write_calibration(role, when, frames)
            for frame in frames:
                self._discard(frame)
        return arrival

    def _calibration_frames(self, which: tuple[str, str], lighting: Lighting, exposures: list[float]) -> list[RawFrame]:
        """One calibration set's frames, the lights in ``lighting``."""
        role, when = which
        self._switch(lighting)
        frames: list[RawFrame] = []
        for k, exposure in enumerate(exposures):
            self._checkpoint()
            self._set_step(
                f"calibration: {role} frames {when} the sweep ({lighting.describe()}), "
                f"frame {k + 1} of {len(exposures)}"
            )
            frame = self._device("calibration capture", self.context.devices.camera.capture, exposure)
            frames.append(frame)
            self.context.show_frame(self.run_id, frame)
        return frames

    def _ready_for_sweep(self, calibrates: bool) -> None:
        """The light on and the room dark before the sweep: after calibration frames, or whenever
        the switch left them otherwise. A switch whose state is unknown (a manual one when the
        daemon has just started) is left alone unless the run takes calibration frames."""
        switch = self.context.devices.light
        if switch.takes_calibration and switch.state != SWEEP and (switch.state is not None or calibrates):
            self._switch(SWEEP)

    def _switch(self, lighting: Lighting) -> None:
        """Put the lights in ``lighting``: at once, or once the operator has done it and resumed."""
        switch = self.context.devices.light
        if switch.state == lighting:
            return
        instruction = switch.instruction(lighting)
        if instruction is not None:
            self._wait_for_operator(instruction)
        self._device("light switch", switch.set, lighting)

    def _wait_for_operator(self, instruction: str) -> None:
        """Pause the run, saying what the operator must do; return when it is resumed."""
        log.info("run %s paused for the operator: %s", self.run_id, instruction)
        with self.context.lock:
            if self.context.catalog.get_run(self.run_id).state != "paused":
                self.context.catalog.transition_run(self.run_id, "paused")
            self.control.pause.set()
        self._set_step(f"waiting for the operator: {instruction}")
        self._checkpoint()

    # --- between frames ----------------------------------------------------------------------
    def _checkpoint(self) -> None:
        """Between frames: honour abort, and wait while paused."""
        control = self.control
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
            with self.context.lock:
                if not self.control.pause.is_set():
                    self.finishing = True
                    return

    def _device(self, what: str, action: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        """Run a device action, retrying transient errors."""
        control = self.control
        attempts = self.context.settings.device_retries + 1
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
                self.context.sleep(0.2 * (attempt + 1))
        raise AssertionError("unreachable")

    def _set_step(self, step: str) -> None:
        self.step = step
        self.context.events.publish()

    def _discard(self, frame: RawFrame) -> None:
        discard_raw(frame, self.context.settings.camera.keep_raw_files)

    # --- writing behind the arm, and the run's end ----------------------------------------
    def _write_loop(self, writer: RunFileWriter, behind: WriteBehind) -> None:
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
                        self._discard(frame)
                    recent = behind.durations[-10:]
                    self.context.catalog.update_progress(
                        self.run_id,
                        positions_done=int(writer.complete.sum()),
                        current_position=index if self.position is None else self.position,  # where the arm is
                        seconds_per_position=sum(recent) / len(recent) if behind.durations else None,
                        exposures_per_position=len(frames),
                    )
                except BaseException as exc:  # noqa: BLE001 - reported to the run thread
                    behind.errors.append(exc)
                    continue
                self.context.events.publish()
            finally:
                behind.queue.task_done()

    def _end_run(self, outcome: str, message: str, writer: RunFileWriter | None, behind: WriteBehind) -> None:
        """However the run ended: stop the arm unless it completed, write the frames already
        taken, and record the outcome in the run file and the catalog; then the queue's turn."""
        context = self.context
        with context.lock:
            self.finishing = True  # a pause, resume or abort no longer applies (409)
        if outcome != "complete":
            try:
                context.devices.arm.stop()
            except DeviceError as exc:
                message += f"; stopping the arm also failed: {exc}"
        if behind.thread is not None and behind.thread.is_alive():
            behind.queue.put(None)  # frames already taken are still written
            behind.thread.join()
        if behind.errors and outcome == "complete":
            outcome, message = "failed", failure_message(behind.errors[0], None)
        if writer is not None:
            outcome, message = self._close_run_file(writer, outcome, message)
        # The end recorded and the rig released in one step: a request sees the run in
        # progress, or ended with the engine free and the queue moved on.
        with context.lock:
            # No step from here: a status reads the catalog, then the step, without the lock, and
            # must not find the run ended and still at a step.
            self.step = None
            context.pending.record(self.run_id, outcome, message)
            level = logging.INFO if outcome == "complete" else logging.WARNING
            log.log(level, "run %s %s%s", self.run_id, outcome, f": {message}" if message else "")
            self.exiting = True
            context.ended(self.run_id, outcome, message)
        context.events.publish()

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
