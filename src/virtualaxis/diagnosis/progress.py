"""Progress of a diagnosis as typed events: which stage runs, in which selection round, how many candidates it
fits and how many are done. A caller renders them (the CLI: a bar on a terminal, a line per stage in a log);
nothing parses text."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

#: the stages of a run, in order (``screen``, ``refine`` and ``joint_refit`` repeat once per selection round)
STAGES = ("read", "controller_check", "baseline", "localise", "screen", "refine", "joint_refit", "verify", "hybrid")

_TITLES = {
    "read": "reading and checking the traces",
    "controller_check": "checking the controller",
    "baseline": "simulating the nominal model",
    "localise": "locating the residual",
    "screen": "screening",
    "refine": "refining",
    "joint_refit": "joint refit",
    "verify": "verifying the calibrated model",
    "hybrid": "fitting the data-driven residual models",
}


@dataclass(frozen=True)
class ProgressEvent:
    """One step of a diagnosis.

    ``kind`` is ``"start"`` when a stage begins (``total``: the candidates it fits, 0 for a single step) and
    ``"item"`` when one candidate of it is done (``done`` of ``total``, ``effect`` names it). ``round`` is the
    selection round (1-based) of ``screen``/``refine``/``joint_refit``, 0 elsewhere; ``effects`` names what a
    joint refit refits together."""

    stage: str
    kind: str = "start"
    round: int = 0
    total: int = 0
    done: int = 0
    effect: str = ""
    effects: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.stage not in STAGES:
            raise ValueError(f"unknown diagnosis stage {self.stage!r}")
        if self.kind not in ("start", "item"):
            raise ValueError(f"unknown progress event kind {self.kind!r}")

    def describe(self) -> str:
        """One line for a log: ``round 2: joint refit of backlash + coulomb_friction``."""
        head = f"round {self.round}: " if self.round else ""
        title = _TITLES[self.stage]
        if self.kind == "item":
            return f"{head}{title} {self.done}/{self.total}: {self.effect}"
        if self.stage == "joint_refit":
            return f"{head}{title} of {' + '.join(self.effects)}"
        if self.total:
            return f"{head}{title} {self.total} candidate{'s' if self.total != 1 else ''}"
        return f"{head}{title}"


ProgressFn = Callable[[ProgressEvent], None]


def item_counter(progress: ProgressFn | None, stage: str, round_no: int, total: int) -> Callable | None:
    """A per-candidate callback for :meth:`Runner.map <virtualaxis.diagnosis.fit.Runner.map>` that sends
    ``item`` events numbered 1..total; None without ``progress``."""
    if progress is None:
        return None
    done = [0]

    def one(result) -> None:
        done[0] += 1
        progress(ProgressEvent(stage, "item", round_no, total, done[0], getattr(result, "effect", "")))

    return one
