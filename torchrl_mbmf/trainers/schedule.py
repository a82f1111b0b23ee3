"""The phase schedule of a run: which policy acts, when the model refits, when planning ends.

The phases of each method: ``docs/design/loop.md``.
"""

from __future__ import annotations

import dataclasses
import enum
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from omegaconf import DictConfig

if TYPE_CHECKING:
    from torchrl_mbmf.trainers.settings import TrainConfig

__all__ = ["Actor", "Phase", "PhaseSchedule", "Progress"]


class Phase(enum.StrEnum):
    """A run's phase (its value is what checkpoints store).

    Args:
        *args: the member's value, e.g. ``Phase("random")``.
        **kwds: none (the ``enum`` signature).

    Examples:
        >>> from torchrl_mbmf.trainers.schedule import Phase
        >>> Phase("planning") is Phase.PLANNING
        True
    """

    RANDOM = "random"
    PLANNING = "planning"
    MODEL_FREE = "model_free"


class Actor(enum.Enum):
    """Which policy collects the real steps.

    Args:
        *args: the member's value, e.g. ``Actor("random")``.
        **kwds: none (the ``enum`` signature).

    Examples:
        >>> from torchrl_mbmf.trainers.schedule import Actor
        >>> [a.value for a in Actor]
        ['random', 'planner', 'agent']
    """

    RANDOM = "random"
    PLANNER = "planner"
    AGENT = "agent"


#: Entries written only once set (a checkpoint without them predates the first fit).
_OPTIONAL_ENTRIES: tuple[str, ...] = ("config", "disagreement_threshold", "last_fit_transitions")


@dataclass
class Progress:
    """The loop's state: counts, phase, next due steps; what a checkpoint's ``progress`` holds.

    Args:
        real_steps: real env steps so far, random-data steps included.
        random_steps: random-policy steps of the first model's data.
        updates: agent updates so far.
        phase: the :class:`Phase` value.
        episodes: finished training episodes.
        last_returns: returns of the last finished episodes (up to 10).
        next_eval: real step of the next evaluation.
        next_checkpoint: real step of the next checkpoint.
        next_refit: real step of the next step-based refit (SAC methods).
        switch_step: real step at which planning ended (``None`` before).
        fingerprint: settings a checkpoint must agree on (older checkpoints).
        config: the flattened config the run was written with (``None``: predates it).
        disagreement_threshold: the calibrated ensemble threshold (``None``: not calibrated).
        last_fit_transitions: the dataset's length at the last model fit (``None``: no fit).
        extra: entries of an older or newer checkpoint this class does not know.

    Examples:
        >>> from torchrl_mbmf.trainers.schedule import Progress
        >>> progress = Progress(real_steps=400, phase="planning")
        >>> progress.real_steps += 200
        >>> saved = progress.to_dict()
        >>> restored = Progress()
        >>> restored.load_dict(saved)
        >>> restored == progress, restored["real_steps"]
        (True, 600)
    """

    real_steps: int = 0
    random_steps: int = 0
    updates: int = 0
    phase: str = Phase.MODEL_FREE.value
    episodes: int = 0
    last_returns: list[float] = field(default_factory=list)
    next_eval: int = 0
    next_checkpoint: int = 0
    next_refit: int = 0
    switch_step: int | None = None
    fingerprint: dict[str, Any] = field(default_factory=dict)
    config: dict[str, Any] | None = None
    disagreement_threshold: float | None = None
    last_fit_transitions: int | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def _names(cls) -> tuple[str, ...]:
        return tuple(f.name for f in dataclasses.fields(cls) if f.name != "extra")

    def to_dict(self) -> dict[str, Any]:
        """The JSON object a checkpoint stores (unset optional entries left out)."""
        out = {name: getattr(self, name) for name in self._names()}
        for name in _OPTIONAL_ENTRIES:
            if out[name] is None:
                del out[name]
        return {**self.extra, **out}

    def load_dict(self, value: Mapping[str, Any]) -> None:
        """Replaces the whole state with a stored one (entries it lacks take their defaults).

        Args:
            value: a stored progress record (:meth:`to_dict`, or an older checkpoint's).
        """
        fresh = Progress()
        names = self._names()
        for name in names:
            setattr(self, name, value.get(name, getattr(fresh, name)))
        self.extra = {k: v for k, v in value.items() if k not in names}

    def __getitem__(self, key: str) -> Any:
        if key in self._names():
            return getattr(self, key)
        return self.extra[key]

    def __setitem__(self, key: str, value: Any) -> None:
        if key in self._names():
            setattr(self, key, value)
        else:
            self.extra[key] = value

    def get(self, key: str, default: Any = None) -> Any:
        """The entry ``key`` (a field or an extra entry), ``default`` if unset.

        Args:
            key: the entry's name.
            default: returned when the entry is missing or ``None``. Defaults to ``None``.
        """
        try:
            value = self[key]
        except KeyError:
            return default
        return default if value is None else value


@dataclass(frozen=True)
class PhaseSchedule:
    """When each phase starts and ends and when the world model refits (reads a :class:`Progress`).

    Args:
        model_based: whether the run has a world model (starts in ``Phase.RANDOM``).
        planning_updates: updates after which planning ends, ``None`` to plan to the end.
        refit_every_updates: refit every this many updates while planning (PPO methods).
        refit_every_steps: refit every this many real steps while planning (SAC methods).
        init_random_frames: real steps a model-free run acts randomly first.

    Examples:
        >>> from torchrl_mbmf.trainers.schedule import Actor, Phase, PhaseSchedule, Progress
        >>> schedule = PhaseSchedule(model_based=True, planning_updates=2, refit_every_updates=1)
        >>> progress = Progress(phase=schedule.first_phase().value)
        >>> schedule.phase(progress), schedule.actor(progress)
        (<Phase.RANDOM: 'random'>, <Actor.RANDOM: 'random'>)
        >>> progress.phase, progress.updates = "planning", 2
        >>> schedule.switch_due(progress)
        True
    """

    model_based: bool
    planning_updates: int | None = None
    refit_every_updates: int | None = None
    refit_every_steps: int | None = None
    init_random_frames: int = 0

    def __post_init__(self) -> None:
        for name in ("planning_updates", "refit_every_updates", "refit_every_steps"):
            value = getattr(self, name)
            if value is not None and (not isinstance(value, int) or value < 1):
                raise ValueError(f"PhaseSchedule: {name} must be an integer >= 1, got {value!r}")
        if self.init_random_frames < 0:
            raise ValueError(
                f"PhaseSchedule: init_random_frames must be >= 0, got {self.init_random_frames}"
            )

    @classmethod
    def from_config(cls, cfg: DictConfig | TrainConfig) -> PhaseSchedule:
        """The schedule of ``cfg.method``: each method reads only its own settings.

        Args:
            cfg: the training config or its parsed
                :class:`~torchrl_mbmf.trainers.settings.TrainConfig`.

        Examples:
            >>> from omegaconf import OmegaConf
            >>> cfg = OmegaConf.create({"method": "sac_mpc", "sac": {"refit_every_steps": 50}})
            >>> PhaseSchedule.from_config(cfg).refit_every_steps
            50
        """
        method = cfg.method
        if method in ("mpc", "ppo_mpc"):
            return cls(
                model_based=True,
                planning_updates=int(cfg.planning_updates),
                refit_every_updates=int(cfg.world_model.refit_every),
            )
        if method == "sac_mpc":
            return cls(model_based=True, refit_every_steps=int(cfg.sac.refit_every_steps))
        if method == "sac_mbpo":  # its "planner" is the actor (acts in the planning phase)
            return cls(model_based=True, refit_every_steps=int(cfg.mbpo.refit_every))
        if method == "sac":
            return cls(model_based=False, init_random_frames=int(cfg.sac.init_random_frames))
        return cls(model_based=False)

    def first_phase(self) -> Phase:
        """The phase a fresh run starts in."""
        return Phase.RANDOM if self.model_based else Phase.MODEL_FREE

    @staticmethod
    def phase(progress: Progress) -> Phase:
        """The phase recorded in ``progress``."""
        return Phase(progress.phase)

    def actor(self, progress: Progress) -> Actor:
        """Which policy collects the next real steps."""
        phase = self.phase(progress)
        if phase is Phase.PLANNING:
            return Actor.PLANNER
        if phase is Phase.RANDOM or progress.real_steps < self.init_random_frames:
            return Actor.RANDOM
        return Actor.AGENT

    def planning_done(self, progress: Progress) -> bool:
        """Whether the planning phase has run its ``planning_updates`` updates."""
        return self.planning_updates is not None and progress.updates >= self.planning_updates

    def switch_due(self, progress: Progress) -> bool:
        """Whether the run is planning and its planning phase is over (warm start next)."""
        return self.phase(progress) is Phase.PLANNING and self.planning_done(progress)

    def start_planning(self, progress: Progress) -> None:
        """Ends the random-data phase: planning from here, the first step-based refit set."""
        progress.phase = Phase.PLANNING.value
        if self.refit_every_steps is not None:
            progress.next_refit = progress.real_steps + self.refit_every_steps

    def start_model_free(self, progress: Progress) -> None:
        """Ends planning: the agent alone acts from here (records ``switch_step``)."""
        progress.phase = Phase.MODEL_FREE.value
        progress.switch_step = progress.real_steps

    def dataset_needed(self, progress: Progress) -> bool:
        """Whether the real-transition dataset can still be used (a checkpoint must hold it).

        Args:
            progress: the progress record.

        Examples:
            >>> from torchrl_mbmf.trainers.schedule import PhaseSchedule, Progress
            >>> s = PhaseSchedule(model_based=True, planning_updates=2, refit_every_updates=1)
            >>> s.dataset_needed(Progress(phase="planning")), s.dataset_needed(Progress())
            (True, False)
        """
        return self.model_based and self.phase(progress) is not Phase.MODEL_FREE

    def refit_due(self, progress: Progress, planned: bool) -> bool:
        """After an update: whether the model refits now (advances ``next_refit`` if so).

        Args:
            progress: the progress record, counts of the batch just used included.
            planned: whether the batch was collected by the planner.
        """
        if not planned:
            return False
        if self.refit_every_updates is not None:
            # no refit once the planning phase is over: nothing plans with it again
            due = progress.updates % self.refit_every_updates == 0
            return due and not self.planning_done(progress)
        if self.refit_every_steps is not None and progress.real_steps >= progress.next_refit:
            progress.next_refit += self.refit_every_steps
            return True
        return False

    def round_over(self, progress: Progress, actor: Actor) -> bool:
        """Whether the collector that ``actor`` runs stops after the batch just used."""
        return actor is Actor.RANDOM or self.switch_due(progress) or self.actor(progress) != actor
