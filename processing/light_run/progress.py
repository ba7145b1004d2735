"""The steps of a light run's processing, and how each says how far it is.

:func:`~processing.light_run.run.process_run` calls its ``progress(step, done, total)`` as
every step starts (``done = 0``) and as it advances: the steps over the positions
(``hdr``, ``estimate``) after every position, the others once more when they end
(``1`` of ``1``). ``step`` is one of :data:`STEPS`' names, in their order; a step the
processing does not need is not reported (``calibration``, ``layout`` and ``camera`` are
three ways of settling the sources: one of them runs, or none with a layout and no fits).
``exports`` and ``report`` run side by side (the light files on a thread while the report
is drawn): ``exports`` starts first.

A callable of two parameters, ``progress(done, total)``, is called as before the steps
were named: after every position task, counted over the passes over the positions.
"""

from __future__ import annotations

import inspect
import threading
from collections.abc import Callable
from dataclasses import dataclass


@dataclass(frozen=True)
class Step:
    """One step: its name, what people read, what it counts, and its share of a whole
    processing (for a job's progress, 0..1)."""

    name: str
    label: str
    unit: str
    weight: float


#: Every step in the order it runs. The weights are rough shares of the wall time of the
#: demo's processing (66 positions, layout searched, self-calibration on), for a job's
#: overall progress; a step that does not run leaves its share to the next.
STEPS: tuple[Step, ...] = (
    Step("checksums", "frame checksums", "", 0.02),
    Step("noise", "noise model", "", 0.03),
    Step("hdr", "HDR merge", "positions", 0.40),
    Step("calibration", "self-calibration (layout search and rig fit)", "", 0.15),
    Step("layout", "layout search", "", 0.15),
    Step("camera", "camera fit", "", 0.15),
    Step("point-spread", "point spread refined from the sweep", "", 0.03),
    Step("estimate", "source estimate", "positions", 0.17),
    Step("fits", "fits", "", 0.05),
    Step("exports", "light files (IES, LDT, TM-25)", "", 0.05),
    Step("report", "report", "", 0.10),
)
BY_NAME = {step.name: step for step in STEPS}
#: The steps that settle the sources: one slot of the order, whichever of them runs.
_SETTLING = ("calibration", "layout", "camera")

#: ``progress(step, done, total)``.
StepProgress = Callable[[str, int, int], None]


def _slot(name: str) -> str:
    return "calibration" if name in _SETTLING else name


def overall_fraction(step: str, done: int, total: int) -> float:
    """The share of a whole processing done when ``step`` has done ``done`` of ``total``:
    the weights of the steps before it, and its own in proportion (0..1).

    Examples
    --------
    >>> overall_fraction("checksums", 0, 1), round(overall_fraction("hdr", 33, 66), 3)
    (0.0, 0.25)
    >>> overall_fraction("estimate", 0, 66) == overall_fraction("point-spread", 1, 1)
    True
    """
    slots: list[str] = []
    for s in STEPS:
        if _slot(s.name) not in slots:
            slots.append(_slot(s.name))
    weight = {slot: BY_NAME[slot].weight for slot in slots}
    here = slots.index(_slot(BY_NAME[step].name))
    before = sum(weight[slot] for slot in slots[:here])
    share = weight[slots[here]] * (min(done, total) / total if total > 0 else 0.0)
    return min(1.0, before + share)


def describe(step: str, done: int, total: int) -> str:
    """A step's progress in words: ``HDR merge: 12 of 66 positions``, ``fits``, ``fits: done``."""
    s = BY_NAME[step]
    if s.unit:
        return f"{s.label}: {done} of {total} {s.unit}"
    return f"{s.label}: done" if total and done >= total else s.label


def takes_steps(progress: Callable[..., None]) -> bool:
    """Whether ``progress`` takes ``(step, done, total)`` (three positional parameters) rather
    than ``(done, total)``."""
    try:
        signature = inspect.signature(progress)
    except (TypeError, ValueError):  # a builtin without a signature: the current form
        return True
    try:
        signature.bind("step", 0, 1)
    except TypeError:
        return False
    return True


class Steps:
    """The processing's side of ``progress``: names each step, counts its work, and calls
    the callable in either form (thread-safe: the light files are written on a thread).

    Parameters
    ----------
    progress : callable or None
        ``progress(step, done, total)``, or ``progress(done, total)`` (the position tasks
        over every pass, ``positions_total`` in all).
    """

    def __init__(self, progress: Callable[..., None] | None) -> None:
        self._progress = progress
        self._named = progress is not None and takes_steps(progress)
        self._lock = threading.Lock()
        self.order: list[str] = []  # the steps started, in order
        self.positions_done = 0
        self.positions_total = 0

    def start(self, step: str, total: int = 1) -> None:
        """``step`` begins, with ``total`` things to do (positions, or 1)."""
        if step not in BY_NAME:
            raise ValueError(f"unknown processing step {step!r}")
        with self._lock:
            self.order.append(step)
        if self._named:
            self._call(step, 0, total)

    def advance(self, step: str, done: int, total: int) -> None:
        """``step`` has done ``done`` of ``total``."""
        if self._named:
            self._call(step, done, total)
        elif self._progress is not None and BY_NAME[step].unit == "positions":
            with self._lock:
                self.positions_done += 1
            self._progress(self.positions_done, self.positions_total)

    def end(self, step: str) -> None:
        """``step`` (one of those counted as one thing) has ended."""
        self.advance(step, 1, 1)

    def _call(self, step: str, done: int, total: int) -> None:
        assert self._progress is not None
        self._progress(step, done, total)
