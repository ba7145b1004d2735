"""The processing steps, by name: what ``--steps`` and a job's ``steps`` may say.

Two steps do the work (``processing.light_run``):

``hdr``
    merge each position's bracket into radiance with its variance (the results file, an
    OpenEXR and a PNG per position);
``sources``
    everything after it, per position and then per run: trace the chief rays, unmix the
    sources with templates (or sum cells), fit every source's I(θ), write the light model,
    the IES, LDT and TM-25 files and the report.

``trace`` and ``fit`` (``docs/measurement.md``'s names for the stages after the merge, which
catalog jobs may say: ``hdr,trace,fit``) are accepted as names for parts of ``sources``, and
either one, or both, selects it. This module imports nothing heavy, so that the daemon can
check a job request without loading the processing.
"""

from __future__ import annotations

from collections.abc import Iterable
from enum import StrEnum


class Step(StrEnum):
    """A processing step (its value is its name on the command line and in a job)."""

    HDR = "hdr"
    SOURCES = "sources"


#: The steps, in the order they run.
STEPS: tuple[Step, ...] = tuple(Step)
#: Older or finer-grained names, and the step that does that work.
STEP_ALIASES: dict[str, str] = {"trace": "sources", "fit": "sources"}
#: What a job does when it does not say: everything.
DEFAULT_STEPS = "hdr,sources"


class StepsError(ValueError):
    """A step list naming an unknown step (one line)."""


def resolve_steps(steps: str | Iterable[str]) -> tuple[Step, ...]:
    """The steps a list names, aliases resolved, each once, in the order they run.

    Parameters
    ----------
    steps : str or iterable of str
        ``"hdr,sources"``, ``"hdr,trace,fit"``, ``("hdr",)``, ...; blanks are ignored.

    Returns
    -------
    tuple of Step
        A non-empty subsequence of :data:`STEPS`.

    Raises
    ------
    StepsError
        An unknown name, or no name at all.

    Examples
    --------
    >>> resolve_steps("fit,hdr")
    (<Step.HDR: 'hdr'>, <Step.SOURCES: 'sources'>)
    >>> resolve_steps("hdr,trace,fit") == resolve_steps("hdr,sources")
    True
    """
    names = steps.split(",") if isinstance(steps, str) else list(steps)
    wanted = set()
    for raw in names:
        name = str(raw).strip()
        if not name:
            continue
        if name not in STEPS and name not in STEP_ALIASES:
            raise StepsError(
                f"unknown step {name!r} (known: {', '.join(STEPS)}; {' and '.join(STEP_ALIASES)} are part of sources)"
            )
        wanted.add(STEP_ALIASES.get(name, name))
    if not wanted:
        raise StepsError(f"no step named (known: {', '.join(STEPS)})")
    return tuple(step for step in STEPS if step in wanted)
