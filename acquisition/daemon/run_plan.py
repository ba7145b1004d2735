"""What a run is made of while the engine takes it: its plan (the poses, the request, the
calibration and bracket rules, the files it belongs with), the hand-over to the thread that
writes behind the arm, the arm's arrivals, and the calibration sets the plan names."""

from __future__ import annotations

import json
import queue
import threading
from dataclasses import dataclass, field

from acquisition.daemon.models import FixedBracket, RunRequest
from acquisition.daemon.settings import AutoBracketSettings
from drivers.contracts.rig import Rig
from drivers.light import AMBIENT, DARK, Lighting
from drivers.pose import Pose

#: How a run whose room cannot be darkened takes its dark frames (``RunHeader.calibration``).
DARK_IN_LIT_ROOM = "shortest exposure, room lit"


@dataclass(frozen=True)
class RunPlan:
    """What a run request becomes when its run starts or resumes, worked out once
    (``RunPreflight.plan``) and carried through the run: the rig with the request's schedule,
    the poses it takes, its calibration plan, its auto-bracket rule, and the files it belongs
    with."""

    request: RunRequest
    rig: Rig
    tool_poses: list[Pose]
    light_poses: list[Pose]
    #: The calibration sets the run takes, and how (``RunHeader.calibration``).
    calibration: dict
    #: The auto-bracket rule with the request's overrides; None for a fixed bracket.
    auto_bracket: AutoBracketSettings | None
    #: The files the run belongs with, read once when the run is asked for (``references``);
    #: None for a resumed run, whose file records them (read only if that file must be created).
    references: dict | None = None

    def __post_init__(self) -> None:
        if (self.auto_bracket is None) != isinstance(self.request.bracket, FixedBracket):
            raise ValueError("a run's plan has an auto-bracket rule exactly when its request's bracket is auto")

    @property
    def max_exposures(self) -> int:
        """The most frames a position takes: the fixed bracket's, or the auto rule's cap."""
        bracket = self.request.bracket
        if isinstance(bracket, FixedBracket):
            return len(bracket.exposures_s)
        assert self.auto_bracket is not None  # __post_init__
        return self.auto_bracket.max_exposures


def light_model_record(text: str) -> dict:
    """A light-model file's text as its record; ``ValueError`` if it is not one."""
    model = json.loads(text)
    if not isinstance(model, dict) or model.get("format") != "mirrorgonio-light-model":
        raise ValueError("not a mirrorgonio light model file")
    return model


@dataclass
class WriteBehind:
    """What the run thread shares with the thread that writes each position while the arm
    moves to the next: the hand-over queue (one position deep), the writer's errors, and the
    time each position took (for the ETA)."""

    queue: queue.Queue = field(default_factory=lambda: queue.Queue(maxsize=1))
    errors: list[BaseException] = field(default_factory=list)
    durations: list[float] = field(default_factory=list)
    thread: threading.Thread | None = None


@dataclass
class Arrival:
    """The arm arrived at position ``index``: the pose it read back, and when the move started
    and ended (unix s)."""

    index: int
    measured: Pose
    move_started: float
    in_position: float


def calibration_sets(calibration: dict) -> list[tuple[str, str]]:
    """The ``(role, when)`` sets a run's calibration plan (``RunHeader.calibration``) names."""
    sets = calibration.get("sets", []) if isinstance(calibration, dict) else []
    return [(str(entry[0]), str(entry[1])) for entry in sets if isinstance(entry, list | tuple) and len(entry) == 2]


def calibration_shot(calibration: dict, role: str) -> tuple[Lighting, list[float]]:
    """The lights and the exposures of a calibration set of ``role``, as the run's plan says."""
    if role == "ambient":
        return AMBIENT, [float(t) for t in calibration["ambient_exposures_s"]]
    lighting = AMBIENT if calibration.get("dark") == DARK_IN_LIT_ROOM else DARK
    return lighting, [float(t) for t in calibration["dark_exposures_s"]]
