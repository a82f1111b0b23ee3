"""The phase schedule of a run: which policy acts, when the model refits, when planning ends.

Every method runs through the same phases (:class:`Phase`): model-based methods start with
random-policy data for the first world model (``RANDOM``), plan (``PLANNING``) and, for
``mpc`` / ``ppo_mpc``, switch to the agent alone after ``planning_updates`` updates
(``MODEL_FREE``, the warm start); ``sac_mpc`` plans to the end; model-free methods start in
``MODEL_FREE``, SAC acting randomly for its first ``sac.init_random_frames`` frames.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping, MutableMapping
from dataclasses import dataclass
from typing import Any

__all__ = ["Actor", "Phase", "PhaseSchedule"]


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


@dataclass(frozen=True)
class PhaseSchedule:
    """When each phase starts and ends and when the world model refits.

    A progress record (the checkpointed ``dict`` of the loop) holds the state: ``phase``,
    ``real_steps``, ``updates`` and ``next_refit``; the schedule only reads and advances it.

    Args:
        model_based: whether the run has a world model (starts in ``Phase.RANDOM``).
        planning_updates: updates after which planning ends, ``None`` to plan to the end.
        refit_every_updates: refit every this many updates while planning (PPO methods).
        refit_every_steps: refit every this many real steps while planning (SAC methods).
        init_random_frames: real steps a model-free run acts randomly first.

    Examples:
        >>> from torchrl_mbmf.trainers.schedule import Actor, Phase, PhaseSchedule
        >>> schedule = PhaseSchedule(model_based=True, planning_updates=2, refit_every_updates=1)
        >>> progress = {"phase": schedule.first_phase().value, "real_steps": 0, "updates": 0}
        >>> schedule.phase(progress), schedule.actor(progress)
        (<Phase.RANDOM: 'random'>, <Actor.RANDOM: 'random'>)
        >>> progress.update(phase="planning", updates=2)
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
    def from_config(cls, cfg: Any) -> PhaseSchedule:
        """The schedule of ``cfg.method``: each method reads only its own settings.

        Args:
            cfg: the training config.

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
        if method == "sac":
            return cls(model_based=False, init_random_frames=int(cfg.sac.init_random_frames))
        return cls(model_based=False)

    def first_phase(self) -> Phase:
        """The phase a fresh run starts in."""
        return Phase.RANDOM if self.model_based else Phase.MODEL_FREE

    @staticmethod
    def phase(progress: Mapping[str, Any]) -> Phase:
        """The phase recorded in ``progress``."""
        return Phase(progress["phase"])

    def actor(self, progress: MutableMapping[str, Any]) -> Actor:
        """Which policy collects the next real steps."""
        phase = self.phase(progress)
        if phase is Phase.PLANNING:
            return Actor.PLANNER
        if phase is Phase.RANDOM or progress["real_steps"] < self.init_random_frames:
            return Actor.RANDOM
        return Actor.AGENT

    def planning_done(self, progress: MutableMapping[str, Any]) -> bool:
        """Whether the planning phase has run its ``planning_updates`` updates."""
        return self.planning_updates is not None and progress["updates"] >= self.planning_updates

    def switch_due(self, progress: MutableMapping[str, Any]) -> bool:
        """Whether the run is planning and its planning phase is over (warm start next)."""
        return self.phase(progress) is Phase.PLANNING and self.planning_done(progress)

    def start_planning(self, progress: MutableMapping[str, Any]) -> None:
        """Ends the random-data phase: planning from here, the first step-based refit set."""
        progress["phase"] = Phase.PLANNING.value
        if self.refit_every_steps is not None:
            progress["next_refit"] = progress["real_steps"] + self.refit_every_steps

    def start_model_free(self, progress: MutableMapping[str, Any]) -> None:
        """Ends planning: the agent alone acts from here (records ``switch_step``)."""
        progress["phase"] = Phase.MODEL_FREE.value
        progress["switch_step"] = progress["real_steps"]

    def dataset_needed(self, progress: Mapping[str, Any]) -> bool:
        """Whether the real-transition dataset can still be used (a checkpoint must hold it).

        Only a model-based run that has switched to the model-free phase is done with it:
        nothing refits the model there, so its checkpoints leave the dataset out and stay
        small (about the agent's and the model's weights).

        Args:
            progress: the progress record.

        Examples:
            >>> from torchrl_mbmf.trainers.schedule import PhaseSchedule
            >>> s = PhaseSchedule(model_based=True, planning_updates=2, refit_every_updates=1)
            >>> s.dataset_needed({"phase": "planning"}), s.dataset_needed({"phase": "model_free"})
            (True, False)
        """
        return self.model_based and self.phase(progress) is not Phase.MODEL_FREE

    def refit_due(self, progress: MutableMapping[str, Any], planned: bool) -> bool:
        """After an update: whether the model refits now (advances ``next_refit`` if so).

        Args:
            progress: the progress record, counts of the batch just used included.
            planned: whether the batch was collected by the planner.
        """
        if not planned:
            return False
        if self.refit_every_updates is not None:
            # no refit once the planning phase is over: nothing plans with it again
            due = progress["updates"] % self.refit_every_updates == 0
            return due and not self.planning_done(progress)
        if self.refit_every_steps is not None and progress["real_steps"] >= progress["next_refit"]:
            progress["next_refit"] += self.refit_every_steps
            return True
        return False

    def round_over(self, progress: MutableMapping[str, Any], actor: Actor) -> bool:
        """Whether the collector that ``actor`` runs stops after the batch just used.

        It stops when the policy changes (the phase switch included) and after every batch
        of random actions: each such batch comes from freshly seeded envs.
        """
        return actor is Actor.RANDOM or self.switch_due(progress) or self.actor(progress) != actor
