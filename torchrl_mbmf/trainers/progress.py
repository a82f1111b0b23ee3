"""An honest ETA for a run, from the phases it will go through and their measured rates.

Why and how: ``docs/design/loop.md`` (the progress bar's ETA).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from omegaconf import DictConfig
from tensordict import TensorDictBase

from torchrl_mbmf.moved import moved_attribute
from torchrl_mbmf.runs import summary_text
from torchrl_mbmf.trainers.schedule import Actor

if TYPE_CHECKING:
    from torchrl_mbmf.trainers.settings import TrainConfig

__all__ = [
    "BAR_FORMAT",
    "PhaseETA",
    "RunPlan",
    "TrainerETA",
]

#: Names that moved to another module (kept here for one release, with a warning).
MOVED_NAMES: dict[str, str] = {
    "end_of_run_message": "torchrl_mbmf.runs.summary_text",
    "format_seconds": "torchrl_mbmf.runs.summary_text",
}

#: ``tqdm``'s default layout without its step-rate ETA (``{remaining}``); ours is the postfix.
BAR_FORMAT = "{l_bar}{bar}| {n_fmt}/{total_fmt} [{elapsed}, {rate_fmt}{postfix}]"


@dataclass(frozen=True)
class RunPlan:
    """What a run will do, in real steps: who acts over which steps, and when the model fits.

    Args:
        total_steps: the run's real-step budget.
        segments: ``(actor, start, end)`` real-step ranges, in order, covering the budget.
        fits: dataset sizes (real transitions) of every world-model fit, the first included.

    Examples:
        >>> from torchrl_mbmf.trainers.progress import RunPlan
        >>> from torchrl_mbmf.trainers.schedule import Actor
        >>> plan = RunPlan(100, ((Actor.RANDOM, 0, 20), (Actor.PLANNER, 20, 100)), (20, 60))
        >>> plan.steps_left(Actor.PLANNER, 50), plan.fits_left(50)
        (50, (60,))
    """

    total_steps: int
    segments: tuple[tuple[Actor, int, int], ...]
    fits: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        if self.total_steps < 1:
            raise ValueError(f"RunPlan: total_steps must be >= 1, got {self.total_steps}")
        for actor, start, end in self.segments:
            if not isinstance(actor, Actor) or not 0 <= start <= end:
                raise ValueError(
                    f"RunPlan: a segment must be (Actor, start, end) with 0 <= start <= end, "
                    f"got {(actor, start, end)!r}"
                )

    @classmethod
    def from_config(cls, cfg: DictConfig | TrainConfig) -> RunPlan:
        """The plan of a ``train`` config, as :class:`~torchrl_mbmf.trainers.loop.Trainer` runs it.

        Args:
            cfg: the composed training config or its parsed
                :class:`~torchrl_mbmf.trainers.settings.TrainConfig`.

        Examples:
            >>> from omegaconf import OmegaConf
            >>> from torchrl_mbmf.trainers.progress import RunPlan
            >>> cfg = OmegaConf.create({"method": "ppo_mpc", "total_steps": 1000000,
            ...     "planning_updates": 200, "env": {"num_envs": 1},
            ...     "world_model": {"random_steps": 10000, "refit_every": 50},
            ...     "ppo": {"frames_per_batch": 2048}})
            >>> plan = RunPlan.from_config(cfg)
            >>> [(a.value, s, e) for a, s, e in plan.segments]
            [('random', 0, 10000), ('planner', 10000, 419600), ('agent', 419600, 1000000)]
            >>> plan.fits
            (10000, 112400, 214800, 317200)
        """
        method, total = str(cfg.method), int(cfg.total_steps)
        family = "sac" if method.startswith("sac") else "ppo"
        batch = int(getattr(cfg, family).frames_per_batch)
        if method in ("ppo", "sac"):
            random_end = 0
            if method == "sac":
                random_end = min(total, -(-int(cfg.sac.init_random_frames) // batch) * batch)
            segments = ((Actor.RANDOM, 0, random_end), (Actor.AGENT, random_end, total))
            return cls(total, tuple(s for s in segments if s[2] > s[1]))
        # the random-data phase: batches of up to 1000 steps per env (Trainer.collect_random)
        n = max(1, int(getattr(cfg.env, "num_envs", 1) or 1))
        wanted = int(cfg.world_model.random_steps)
        frames = min(1000 * n, -(-wanted // n) * n)
        random_end = min(total, -(-wanted // frames) * frames)
        fits = [random_end]
        if method in ("sac_mpc", "sac_mbpo"):
            every = int(cfg.sac.refit_every_steps if method == "sac_mpc" else cfg.mbpo.refit_every)
            step, next_fit = random_end, random_end
            next_fit += every
            while step < total:
                step += batch
                if step >= next_fit:
                    fits.append(step)
                    next_fit += every
            segments = ((Actor.RANDOM, 0, random_end), (Actor.PLANNER, random_end, total))
            return cls(total, segments, tuple(fits))
        updates, every = int(cfg.planning_updates), int(cfg.world_model.refit_every)
        planning_end = min(total, random_end + updates * batch)
        fits += [
            random_end + k * batch
            for k in range(every, updates, every)
            if random_end + k * batch < total
        ]
        segments = (
            (Actor.RANDOM, 0, random_end),
            (Actor.PLANNER, random_end, planning_end),
            (Actor.AGENT, planning_end, total),
        )
        return cls(total, tuple(s for s in segments if s[2] > s[1]), tuple(fits))

    def steps_left(self, actor: Actor, real_steps: int) -> int:
        """Real steps ``actor`` still takes after ``real_steps``."""
        return sum(
            max(0, end - max(start, real_steps)) for a, start, end in self.segments if a is actor
        )

    def fits_left(self, real_steps: int) -> tuple[int, ...]:
        """The fits still to come once ``real_steps`` steps are collected (not yet learnt from)."""
        return tuple(p for p in self.fits if p >= real_steps)


@dataclass
class PhaseETA:
    """Remaining time of a :class:`RunPlan` from measured per-actor and per-fit rates.

    Args:
        plan: the run's plan.

    Examples:
        >>> from torchrl_mbmf.trainers.progress import PhaseETA, RunPlan
        >>> from torchrl_mbmf.trainers.schedule import Actor
        >>> plan = RunPlan(100, ((Actor.RANDOM, 0, 20), (Actor.PLANNER, 20, 100)), (20, 60))
        >>> eta = PhaseETA(plan)
        >>> eta.observe_batch(Actor.RANDOM, 20, 0.2)
        >>> eta.remaining(20) is None  # no planned step and no fit measured yet
        True
        >>> eta.observe_fit(20, 2.0)
        >>> eta.observe_batch(Actor.PLANNER, 10, 1.0)
        >>> eta.remaining(30)  # 70 planned steps at 0.1 s, a fit of 60 transitions at 0.1 s
        13.0
    """

    plan: RunPlan
    # the measurements so far: per actor, the agent's updates, the model fits
    seconds: dict[Actor, float] = field(default_factory=dict, init=False)
    steps: dict[Actor, int] = field(default_factory=dict, init=False)
    update_seconds: float = field(default=0.0, init=False)
    update_steps: int = field(default=0, init=False)
    fit_seconds: float = field(default=0.0, init=False)
    fit_transitions: int = field(default=0, init=False)

    def observe_batch(self, actor: Actor, steps: int, seconds: float) -> None:
        """Counts ``steps`` real steps by ``actor`` that took ``seconds`` (fits excluded)."""
        if steps < 0 or seconds < 0:
            raise ValueError(f"steps and seconds must be >= 0, got {steps} and {seconds}")
        self.seconds[actor] = self.seconds.get(actor, 0.0) + seconds
        self.steps[actor] = self.steps.get(actor, 0) + steps

    def observe_update(self, steps: int, seconds: float) -> None:
        """Counts the agent's update on a batch of ``steps`` real steps that took ``seconds``."""
        self.update_steps += steps
        self.update_seconds += seconds

    def observe_fit(self, transitions: int, seconds: float) -> None:
        """Counts a world-model fit on ``transitions`` real transitions that took ``seconds``."""
        self.fit_transitions += transitions
        self.fit_seconds += seconds

    def step_seconds(self, actor: Actor) -> float | None:
        """Seconds per real step of ``actor``: measured, else estimated, else ``None``."""
        if self.steps.get(actor, 0) > 0:
            return self.seconds[actor] / self.steps[actor]
        if actor is Actor.AGENT and self.steps.get(Actor.RANDOM, 0) > 0 and self.update_steps:
            random = self.seconds[Actor.RANDOM] / self.steps[Actor.RANDOM]
            return random + self.update_seconds / self.update_steps
        return None

    def remaining(self, real_steps: int) -> float | None:
        """Seconds left once ``real_steps`` steps are collected, or ``None`` if not known yet."""
        total = 0.0
        for actor in Actor:
            left = self.plan.steps_left(actor, real_steps)
            if left == 0:
                continue
            rate = self.step_seconds(actor)
            if rate is None:
                return None
            total += left * rate
        fits = self.plan.fits_left(real_steps)
        if fits:
            if self.fit_transitions == 0:
                return None
            total += sum(fits) * self.fit_seconds / self.fit_transitions
        return total


class TrainerETA:
    """Feeds a :class:`PhaseETA` from a trainer's ``collected`` stage; returns the bar's text.

    Args:
        plan: the run's plan.
        clock: the time source (seconds). Defaults to :func:`time.perf_counter`.
        start: when the run's first batch started (by ``clock``). Defaults to now.

    Examples:
        >>> from types import SimpleNamespace
        >>> from tensordict import TensorDict
        >>> from torchrl_mbmf.trainers.progress import RunPlan, TrainerETA
        >>> from torchrl_mbmf.trainers.schedule import Actor
        >>> clock = iter([0.0, 10.0]).__next__
        >>> tracker = TrainerETA(RunPlan(40, ((Actor.AGENT, 0, 40),)), clock=clock)
        >>> trainer = SimpleNamespace(acting=Actor.AGENT, progress={"real_steps": 10},
        ...                           times={"refit_s": 0.0, "update_s": 0.0})
        >>> tracker(trainer, TensorDict(batch_size=[10]))
        'ETA 0:00:30'
    """

    def __init__(
        self,
        plan: RunPlan,
        clock: Callable[[], float] = time.perf_counter,
        start: float | None = None,
    ) -> None:
        self.eta, self.clock = PhaseETA(plan), clock
        self.last_time = clock() if start is None else start
        self.last_batch: int | None = None  # steps of the previous batch (None: first call)
        self.last_refit = self.last_update = 0.0

    def __call__(self, trainer: Any, batch: TensorDictBase) -> str:
        """Counts the batch just collected; returns ``"ETA h:mm:ss"``."""
        now, steps, size = self.clock(), int(trainer.progress["real_steps"]), batch.numel()
        refit = float(trainer.times["refit_s"]) - self.last_refit
        update = float(trainer.times["update_s"]) - self.last_update
        if refit > 0:  # fits on the transitions collected before this batch
            self.eta.observe_fit(steps - size, refit)
        if update > 0 and self.last_batch is not None:  # the previous batch's update
            self.eta.observe_update(self.last_batch, update)
        # A resumed run's first batch also carries the start-up: it is not measured.
        if self.last_batch is not None or steps == size:
            self.eta.observe_batch(trainer.acting, size, max(0.0, now - self.last_time - refit))
        self.last_time, self.last_batch = now, size
        self.last_refit, self.last_update = self.last_refit + refit, self.last_update + update
        return f"ETA {summary_text.format_seconds(self.eta.remaining(steps))}"


def __getattr__(name: str) -> object:
    return moved_attribute(__name__, name, MOVED_NAMES)
