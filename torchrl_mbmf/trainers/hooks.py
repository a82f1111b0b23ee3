"""The hooks of the training loop: logging, progress, model refits, evaluation, checkpoints.

Stages (in loop order): ``collected``, ``updated`` and ``round_end``; why our own hook list:
``docs/design/loop.md``.
"""

from __future__ import annotations

import abc
import time
from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
from tensordict import TensorDictBase
from tqdm.auto import tqdm

from torchrl_mbmf.trainers.progress import BAR_FORMAT, RunPlan, TrainerETA
from torchrl_mbmf.trainers.schedule import Actor, Progress

if TYPE_CHECKING:
    from torchrl_mbmf.trainers.loop import Trainer

__all__ = [
    "STAGES",
    "EpisodeLog",
    "Evaluation",
    "Hook",
    "Hooks",
    "ModelData",
    "ModelRefit",
    "ProgressBar",
    "SaveCheckpoint",
    "StepTiming",
]

#: The stages a hook can run at, in loop order.
STAGES: tuple[str, ...] = ("collected", "updated", "round_end")


class Hook(abc.ABC):
    """A step the loop runs once per collected batch at one stage, with the trainer.

    Examples:
        >>> from torchrl_mbmf.trainers.hooks import Hook
        >>> class PrintBatch(Hook):
        ...     def __call__(self, trainer, batch):
        ...         print("batch", batch)
        >>> PrintBatch()(None, 1)
        batch 1
    """

    @abc.abstractmethod
    def __call__(self, trainer: Trainer, batch: TensorDictBase | None) -> None:
        """Runs the hook for ``trainer`` (``batch``: the batch just collected, if any).

        It reads and advances ``trainer.progress`` and uses the trainer's parts (``agent``,
        ``world``, ``schedule``).
        """


#: A hook: a :class:`Hook` or any callable ``(trainer, batch) -> None``.
HookFn = Hook | Callable[["Trainer", TensorDictBase | None], None]


class Hooks:
    """Ordered hooks per stage.

    Examples:
        >>> from torchrl_mbmf.trainers.hooks import Hooks
        >>> hooks, seen = Hooks(), []
        >>> hooks.register("collected", lambda trainer, batch: seen.append(batch))
        >>> hooks.run("collected", None, 1)
        >>> seen
        [1]
    """

    def __init__(self) -> None:
        self.stages: dict[str, list[HookFn]] = {stage: [] for stage in STAGES}

    def register(self, stage: str, hook: HookFn) -> None:
        """Appends ``hook`` (called as ``hook(trainer, batch)``) to ``stage``."""
        if stage not in self.stages:
            raise ValueError(f"stage={stage!r} is not a hook stage; allowed: {list(STAGES)}")
        self.stages[stage].append(hook)

    def run(self, stage: str, trainer: Trainer, batch: TensorDictBase | None = None) -> None:
        """Calls the hooks of ``stage`` in registration order."""
        for hook in self.stages[stage]:
            hook(trainer, batch)


class ProgressBar(Hook):
    """A ``tqdm`` bar of real steps (``collected``); disabled with ``progress=false``.

    Args:
        total: the run's real-step budget.
        desc: the bar's label.
        enabled: whether the bar shows.
        plan: the run's phases for the ETA (:meth:`RunPlan.from_config`,
            :class:`~torchrl_mbmf.trainers.progress.TrainerETA`); ``None``: no ETA. Defaults
            to ``None``.

    Examples:
        >>> from torchrl_mbmf.trainers.hooks import ProgressBar
        >>> ProgressBar(100, "ppo", enabled=False).bar is None
        True
    """

    def __init__(self, total: int, desc: str, enabled: bool, plan: RunPlan | None = None) -> None:
        self.total, self.desc, self.enabled, self.plan = total, desc, enabled, plan
        self.bar: tqdm | None = None
        self.eta: TrainerETA | None = None

    def open(self, initial: int) -> None:
        """Shows the bar from ``initial`` steps."""
        self.bar = tqdm(
            total=self.total,
            initial=initial,
            desc=self.desc,
            unit="step",
            disable=not self.enabled,
            bar_format=BAR_FORMAT,
        )
        self.opened = time.perf_counter()

    def __call__(self, trainer: Trainer, batch: TensorDictBase | None) -> None:
        """Runs the hook for ``trainer`` (``batch``: the batch just collected, if any)."""
        if self.bar is not None:
            if self.enabled and self.plan is not None:
                if self.eta is None:
                    self.eta = TrainerETA(self.plan, start=self.opened)
                self.bar.set_postfix_str(self.eta(trainer, batch), refresh=False)
            self.bar.update(batch.numel())

    def close(self) -> None:
        """Closes the bar."""
        if self.bar is not None:
            self.bar.close()


class EpisodeLog(Hook):
    """Logs each finished episode's return and the last-10 statistics (``collected``).

    Examples:
        >>> from torchrl_mbmf.trainers.hooks import EpisodeLog
        >>> EpisodeLog.WINDOW
        10
    """

    WINDOW = 10

    def __call__(self, trainer: Trainer, batch: TensorDictBase | None) -> None:
        """Runs the hook for ``trainer`` (``batch``: the batch just collected, if any)."""
        progress = trainer.progress
        done = batch.get(("next", "done"))[..., 0]
        if not done.any():
            return
        returns = batch.get(("next", "episode_reward"))[..., 0][done]
        last = deque(progress.last_returns, maxlen=self.WINDOW)
        for r in returns.tolist():
            progress.episodes += 1
            last.append(r)
            trainer.log({"train/episode_return": r})
        progress.last_returns = list(last)
        arr = np.asarray(last)
        trainer.log(
            {
                "train/return_last10_mean": arr.mean(),
                "train/return_last10_min": arr.min(),
                "train/return_last10_max": arr.max(),
                "train/episodes": progress.episodes,
                "train/real_steps_without_random": progress.real_steps - progress.random_steps,
            }
        )


class ModelData(Hook):
    """Adds random-data and planner batches to the world model's dataset and logs the plans.

    Examples:
        >>> from torchrl_mbmf.trainers.hooks import ModelData
        >>> callable(ModelData())
        True
    """

    def __call__(self, trainer: Trainer, batch: TensorDictBase | None) -> None:
        """Runs the hook for ``trainer`` (``batch``: the batch just collected, if any)."""
        if trainer.acting is Actor.AGENT:
            return
        trainer.world.dataset.extend(batch)
        trainer.log(trainer.world.planner_scalars(batch))


class ModelRefit(Hook):
    """Refits the world model when the schedule says so (``updated``).

    Examples:
        >>> from torchrl_mbmf.trainers.hooks import ModelRefit
        >>> callable(ModelRefit())
        True
    """

    def __call__(self, trainer: Trainer, batch: TensorDictBase | None) -> None:
        """Runs the hook for ``trainer`` (``batch``: the batch just collected, if any)."""
        if trainer.schedule.refit_due(trainer.progress, trainer.acting is Actor.PLANNER):
            trainer.refit_model()


class ModelRollouts(Hook):
    """``sac_mbpo``: a round of branched model rollouts when one is due (``collected``).

    Runs after :class:`ModelData` (the batch's real states are start states), before the
    batch's updates; the next round is due ``mbpo.rollout_every`` real steps later
    (``progress["next_rollout"]``, checkpointed).

    Examples:
        >>> from torchrl_mbmf.trainers.hooks import ModelRollouts
        >>> ModelRollouts.NEXT
        'next_rollout'
    """

    #: The progress entry of the next round's real step.
    NEXT = "next_rollout"

    def __call__(self, trainer: Trainer, batch: TensorDictBase | None) -> None:
        """Runs the hook for ``trainer`` (``batch``: the batch just collected, if any)."""
        progress, rollouts = trainer.progress, trainer.rollouts
        if trainer.acting is not Actor.PLANNER or progress.real_steps < progress.get(self.NEXT, 0):
            return
        start = time.perf_counter()
        scalars = rollouts.generate(trainer.world.dataset)
        progress[self.NEXT] = progress.real_steps + rollouts.rollout_every
        seconds = time.perf_counter() - start
        trainer.times["rollout_s"] += seconds
        trainer.log({**scalars, "time/rollout_s": seconds})


class StepTiming(Hook):
    """Logs the batch's learning time and the run's steps per second (``updated``).

    Examples:
        >>> from torchrl_mbmf.trainers.hooks import StepTiming
        >>> StepTiming().start_steps
        0
    """

    def __init__(self) -> None:
        self.start, self.start_steps = time.perf_counter(), 0

    def open(self, steps: int) -> None:
        """Counts the pace from now and ``steps`` real steps."""
        self.start, self.start_steps = time.perf_counter(), steps

    def __call__(self, trainer: Trainer, batch: TensorDictBase | None) -> None:
        """Runs the hook for ``trainer`` (``batch``: the batch just collected, if any)."""
        now = time.perf_counter()
        trainer.log(
            {
                "time/update_s": now - trainer.batch_time,
                "time/steps_per_s": (trainer.progress.real_steps - self.start_steps)
                / max(1e-9, now - self.start),
            }
        )


class Evaluation(Hook):
    """Evaluates the policy alone every ``every`` real steps (``updated``).

    Args:
        every: real steps between two evaluations (the first at the first batch).
        episodes: episodes per evaluation; 0 counts the schedule without evaluating.

    Examples:
        >>> from torchrl_mbmf.trainers.hooks import Evaluation
        >>> Evaluation(every=1000, episodes=0).episodes
        0
    """

    def __init__(self, every: int, episodes: int) -> None:
        self.every, self.episodes = every, episodes

    def __call__(self, trainer: Trainer, batch: TensorDictBase | None) -> None:
        """Runs the hook for ``trainer`` (``batch``: the batch just collected, if any)."""
        progress = trainer.progress
        if progress.real_steps >= progress.next_eval:
            if self.episodes > 0:
                trainer.log({"eval/return": trainer.evaluate()})
            progress.next_eval += self.every

    def next_eval_at(self, real_steps: int, random_steps: int, frames_per_batch: int) -> int:
        """The ``next_eval`` a run with this schedule from its start holds at ``real_steps``.

        Args:
            real_steps: the real steps so far (a checkpoint's).
            random_steps: the random-data steps among them.
            frames_per_batch: real steps per learning batch.

        Examples:
            >>> from torchrl_mbmf.trainers.hooks import Evaluation
            >>> Evaluation(every=320, episodes=1).next_eval_at(480, 0, 160)
            640
        """
        if frames_per_batch < 1 or not 0 <= random_steps <= real_steps:
            raise ValueError(
                "next_eval_at: needs frames_per_batch >= 1 and 0 <= random_steps <= real_steps, "
                f"got {frames_per_batch}, {random_steps}, {real_steps}"
            )
        next_eval = 0
        for step in range(random_steps + frames_per_batch, real_steps + 1, frames_per_batch):
            if step >= next_eval:
                next_eval += self.every
        return next_eval


class SaveCheckpoint(Hook):
    """Writes a checkpoint when one is due, between two collectors (``round_end``).

    Args:
        every: real steps between two checkpoints.

    Examples:
        >>> from torchrl_mbmf.trainers.hooks import SaveCheckpoint
        >>> from torchrl_mbmf.trainers.schedule import Progress
        >>> progress = Progress(real_steps=450, next_checkpoint=400)
        >>> SaveCheckpoint(every=400).due(progress)
        True
    """

    def __init__(self, every: int) -> None:
        self.every = every

    @staticmethod
    def due(progress: Progress) -> bool:
        """Whether the run has passed its next checkpoint step."""
        return progress.real_steps >= progress.next_checkpoint

    def __call__(self, trainer: Trainer, batch: TensorDictBase | None) -> None:
        """Runs the hook for ``trainer`` (``batch``: the batch just collected, if any)."""
        progress = trainer.progress
        if self.due(progress):
            while progress.next_checkpoint <= progress.real_steps:
                progress.next_checkpoint += self.every
            trainer.save_checkpoint()
