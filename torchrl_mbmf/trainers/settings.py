"""The train config parsed once into typed settings, one dataclass per config group.

:meth:`TrainConfig.from_config` validates and parses it; the design: ``docs/design/config.md``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, TypeVar

from omegaconf import DictConfig, ListConfig, OmegaConf

from torchrl_mbmf.checks import ConfigError
from torchrl_mbmf.runs.resume import DEFAULT_TARGETS
from torchrl_mbmf.trainers.components import group_keys, group_target, qualified_error
from torchrl_mbmf.trainers.config import TrainSettings, flatten_config

__all__ = [
    "CheckpointSettings",
    "EnvSettings",
    "GroupSettings",
    "LoggerSettings",
    "MBPOSettings",
    "PPOSettings",
    "PlannerSettings",
    "RewardSettings",
    "SACSettings",
    "TrainConfig",
    "WorldModelSettings",
]

G = TypeVar("G", bound="GroupSettings")


def _plain(node: Any) -> Any:
    """``node`` as plain, resolved containers."""
    if isinstance(node, DictConfig | ListConfig):
        return OmegaConf.to_container(node, resolve=True)
    return node


@dataclass(frozen=True, kw_only=True)
class GroupSettings:
    """A component group's settings: its builder (``_target_``) and the builder's keys.

    Args:
        target: the builder's import path (``_target_``); ``""``: the group's default.
        extra: keys of a custom builder that are not fields. Defaults to ``{}``.

    Examples:
        >>> from torchrl_mbmf.trainers.settings import LoggerSettings
        >>> LoggerSettings.parse({"backend": "csv"}).build(run_dir="out") is not None
        True
    """

    GROUP: ClassVar[str] = ""
    target: str = ""
    extra: Mapping[str, Any] = field(default_factory=dict)

    @classmethod
    def parse(cls: type[G], node: Mapping[str, Any] | DictConfig) -> G:
        """The settings of a group's config node (``_target_`` and keys).

        Args:
            node: the group's node.

        Raises:
            ConfigError: a key the default builder requires is missing.
        """
        values = dict(_plain(node))
        target = str(values.pop("_target_", None) or DEFAULT_TARGETS[cls.GROUP])
        names = {f.name for f in dataclasses.fields(cls)} - {"target", "extra"}
        known = {k: v for k, v in values.items() if k in names}
        extra = {k: v for k, v in values.items() if k not in names}
        try:
            return cls(target=target, extra=extra, **known)
        except TypeError as err:
            raise ConfigError(f"{cls.GROUP}: {err}") from err

    def options(self) -> dict[str, Any]:
        """The builder's keyword arguments: the fields (and extra keys) it accepts."""
        accepted, _ = group_keys(group_target({self.GROUP: {"_target_": self.target}}, self.GROUP))
        values = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        values = {k: v for k, v in values.items() if k not in ("target", "extra")}
        values.update(self.extra)
        return {k: v for k, v in values.items() if k in accepted}

    def build(self, **runtime: Any) -> Any:
        """Calls the builder with :meth:`options` and ``runtime`` (its runtime objects).

        Raises:
            ConfigError: the builder or a constructor refused an argument; the message names
                the config key (``planner.horizon must be ...``).
        """
        builder = group_target({self.GROUP: {"_target_": self.target}}, self.GROUP)
        options = self.options()
        try:
            return builder(**options, **runtime)
        except (TypeError, ValueError) as err:
            error = qualified_error(self.GROUP, list(options), err)
            if error is err:
                raise
            raise error from err


@dataclass(frozen=True, kw_only=True)
class PPOSettings(GroupSettings):
    """The ``ppo`` group (:class:`~torchrl_mbmf.trainers.agents.PPOAgent`'s keys).

    Args:
        frames_per_batch: real steps per update.
        minibatch_size: PPO minibatch.
        epochs: epochs per batch.
        clip_epsilon: PPO clip.
        entropy_coeff: entropy bonus.
        critic_coeff: critic loss weight.
        gamma: discount.
        lmbda: GAE lambda.
        lr: Adam's learning rate.
        max_grad_norm: gradient clip.
        hidden_sizes: MLP widths.
        distribution: the action distribution.
        init_log_std: initial log-std.
        update: the update path. Defaults to ``"stock"``.
        target: see :class:`GroupSettings`.
        extra: see :class:`GroupSettings`.

    Examples:
        >>> from omegaconf import OmegaConf
        >>> ppo = PPOSettings.parse(OmegaConf.load("configs/algo/ppo.yaml"))
        >>> ppo.frames_per_batch, ppo.update
        (2048, 'fused')
    """

    GROUP: ClassVar[str] = "ppo"
    frames_per_batch: int
    minibatch_size: int
    epochs: int
    clip_epsilon: float
    entropy_coeff: float
    critic_coeff: float
    gamma: float
    lmbda: float
    lr: float
    max_grad_norm: float
    hidden_sizes: list[int]
    distribution: str
    init_log_std: float
    update: str = "stock"


@dataclass(frozen=True, kw_only=True)
class SACSettings(GroupSettings):
    """The ``sac`` group (:class:`~torchrl_mbmf.trainers.agents.SACAgent`'s keys).

    Args:
        frames_per_batch: real steps per collected batch.
        utd_ratio: updates per real step.
        batch_size: replay batch.
        init_random_frames: random steps first.
        replay_size: replay capacity.
        hidden_sizes: MLP widths.
        lr: Adam's learning rate.
        gamma: discount.
        tau: target update rate.
        alpha_init: initial temperature.
        refit_every_steps: ``sac_mpc``'s refit period in real steps.
        update: the update path. Defaults to ``"stock"``.
        loss_function: the Q-regression distance. Defaults to ``"smooth_l1"``.
        scale: the actor's scale parameterisation. Defaults to ``"biased_softplus"``.
        target: see :class:`GroupSettings`.
        extra: see :class:`GroupSettings`.

    Examples:
        >>> from omegaconf import OmegaConf
        >>> SACSettings.parse(OmegaConf.load("configs/algo/sac.yaml")).batch_size
        256
    """

    GROUP: ClassVar[str] = "sac"
    frames_per_batch: int
    utd_ratio: float
    batch_size: int
    init_random_frames: int
    replay_size: int
    hidden_sizes: list[int]
    lr: float
    gamma: float
    tau: float
    alpha_init: float
    refit_every_steps: int
    update: str = "stock"
    loss_function: str = "smooth_l1"
    scale: str = "biased_softplus"


@dataclass(frozen=True, kw_only=True)
class WorldModelSettings(GroupSettings):
    """The ``world_model`` group (:class:`~torchrl_mbmf.trainers.planning.WorldModelPart`'s keys).

    Args:
        hidden_sizes: MLP widths.
        lr: Adam's learning rate.
        batch_size: fit batch.
        max_epochs: fit epochs.
        val_fraction: held-out share.
        patience: early stopping.
        random_steps: random-policy steps before the first fit.
        refit_every: refit period in updates (PPO methods).
        save_fits: keep each fit's weights. Defaults to ``True``.
        multi_step: k of the k-step loss. Defaults to ``1``.
        multi_step_weight: its weight. Defaults to ``1.0``.
        early_stopping: the held-out criterion. Defaults to ``"objective"``.
        ensemble_size: members. Defaults to ``1``.
        probabilistic: Gaussian outputs. Defaults to ``False``.
        adaptive_horizon: uncertainty-adaptive horizon. Defaults to ``False``.
        disagreement_quantile: its calibration quantile. Defaults to ``0.9``.
        learn_termination: a learnt termination head (passed where the builder takes it).
            Defaults to ``False``.
        target: see :class:`GroupSettings`.
        extra: see :class:`GroupSettings`.

    Examples:
        >>> from omegaconf import OmegaConf
        >>> wm = WorldModelSettings.parse(OmegaConf.load("configs/world_model/thesis.yaml"))
        >>> wm.random_steps, wm.ensemble_size
        (10000, 1)
    """

    GROUP: ClassVar[str] = "world_model"
    hidden_sizes: list[int]
    lr: float
    batch_size: int
    max_epochs: int
    val_fraction: float
    patience: int
    random_steps: int
    refit_every: int
    save_fits: bool = True
    multi_step: int = 1
    multi_step_weight: float = 1.0
    early_stopping: str = "objective"
    ensemble_size: int = 1
    probabilistic: bool = False
    adaptive_horizon: bool = False
    disagreement_quantile: float = 0.9
    learn_termination: bool = False


@dataclass(frozen=True, kw_only=True)
class PlannerSettings(GroupSettings):
    """The ``planner`` group (:func:`~torchrl_mbmf.trainers.planning.make_planner`'s keys).

    Args:
        num_candidates: candidate sequences.
        horizon: imagined steps.
        discount: score discount. Defaults to ``1.0``.
        terminal_value: add the value of the last state. Defaults to ``False``.
        refinement: ``None``, ``"cem"`` or ``"mppi"``. Defaults to ``None``.
        iterations: refinement rounds. Defaults to ``2``.
        policy_fraction: candidates kept from the policy. Defaults to ``1/3``.
        num_elites: CEM elites. Defaults to ``3``.
        temperature: MPPI temperature. Defaults to ``1.0``.
        min_std: smallest refinement std. Defaults to ``0.05``.
        target: see :class:`GroupSettings`.
        extra: see :class:`GroupSettings`.

    Examples:
        >>> PlannerSettings.parse({"num_candidates": 15, "horizon": 10}).discount
        1.0
    """

    GROUP: ClassVar[str] = "planner"
    num_candidates: int
    horizon: int
    discount: float = 1.0
    terminal_value: bool = False
    refinement: str | None = None
    iterations: int = 2
    policy_fraction: float = 1 / 3
    num_elites: int = 3
    temperature: float = 1.0
    min_std: float = 0.05


@dataclass(frozen=True, kw_only=True)
class LoggerSettings(GroupSettings):
    """The ``logger`` group (:func:`~torchrl_mbmf.trainers.build.make_logger`'s keys).

    Args:
        backend: the logger backend (``""``: none).
        target: see :class:`GroupSettings`.
        extra: see :class:`GroupSettings`.

    Examples:
        >>> LoggerSettings.parse({"backend": "csv"}).backend
        'csv'
    """

    GROUP: ClassVar[str] = "logger"
    backend: str


@dataclass(frozen=True, kw_only=True)
class MBPOSettings(GroupSettings):
    """The ``mbpo`` group (:class:`~torchrl_mbmf.world_model.branched_rollouts.BranchedRollouts`).

    Args:
        rollout_every: real steps between rollout rounds.
        rollout_batch_size: branches per round.
        rollout_horizon: imagined steps per branch.
        model_replay_size: imagined transitions kept.
        real_ratio: real share of each update batch.
        refit_every: real steps between model refits.
        target: see :class:`GroupSettings`.
        extra: see :class:`GroupSettings`.

    Examples:
        >>> from omegaconf import OmegaConf
        >>> MBPOSettings.parse(OmegaConf.load("configs/mbpo/default.yaml")).rollout_horizon
        1
    """

    GROUP: ClassVar[str] = "mbpo"
    rollout_every: int
    rollout_batch_size: int
    rollout_horizon: int
    model_replay_size: int
    real_ratio: float
    refit_every: int


@dataclass(frozen=True)
class EnvSettings:
    """The ``env`` group.

    Args:
        id: the Gymnasium id.
        num_envs: batched training envs.
        device: the envs' device.

    Examples:
        >>> EnvSettings("Pendulum-v1", 2, "cpu").num_envs
        2
    """

    id: str
    num_envs: int
    device: str


@dataclass(frozen=True)
class RewardSettings:
    """The ``reward`` group.

    Args:
        name: the reward's name.
        kwargs: its constructor's keyword arguments. Defaults to ``{}``.

    Examples:
        >>> RewardSettings("head_pen", {"threshold": -0.3}).kwargs["threshold"]
        -0.3
    """

    name: str
    kwargs: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class CheckpointSettings:
    """The ``checkpoint`` group.

    Args:
        every_steps: real steps between two checkpoints.
        keep_last: checkpoints kept.

    Examples:
        >>> CheckpointSettings(400, 2).keep_last
        2
    """

    every_steps: int
    keep_last: int


#: The component groups' settings classes.
GROUPS: dict[str, type[GroupSettings]] = {
    "ppo": PPOSettings,
    "sac": SACSettings,
    "world_model": WorldModelSettings,
    "planner": PlannerSettings,
    "logger": LoggerSettings,
    "mbpo": MBPOSettings,
}


@dataclass(frozen=True)
class TrainConfig:
    """The whole ``train`` config, validated and parsed once (fields named as its keys).

    Args:
        method: the method.
        seed: the seed.
        total_steps: the real-step budget.
        planning_updates: updates that plan (``mpc``, ``ppo_mpc``).
        eval_every: real steps between evaluations.
        eval_episodes: episodes each.
        progress: show the progress bar.
        env: the env group.
        reward: the reward group.
        checkpoint: the checkpoint group.
        ppo: the PPO group.
        sac: the SAC group.
        world_model: the world-model group.
        planner: the planner group.
        logger: the logger.
        settings: the loop's view (:class:`~torchrl_mbmf.trainers.config.TrainSettings`).
        record: the resolved, flattened config (what a resume compares).
        restart: move a finished or foreign run aside. Defaults to ``False``.
        mbpo: the MBPO group (``None``: a config without it). Defaults to ``None``.

    Examples:
        >>> from hydra import compose, initialize_config_dir
        >>> from pathlib import Path
        >>> with initialize_config_dir(str(Path("configs").resolve()), version_base="1.3"):
        ...     cfg = compose("train", overrides=["method=sac", "env=pendulum"])
        >>> config = TrainConfig.from_config(cfg)
        >>> config.sac.batch_size, config.env.id, config.settings.family
        (256, 'Pendulum-v1', 'sac')
    """

    method: str
    seed: int
    total_steps: int
    planning_updates: int
    eval_every: int
    eval_episodes: int
    progress: bool
    env: EnvSettings
    reward: RewardSettings
    checkpoint: CheckpointSettings
    ppo: PPOSettings
    sac: SACSettings
    world_model: WorldModelSettings
    planner: PlannerSettings
    logger: LoggerSettings
    settings: TrainSettings
    record: dict[str, Any]
    restart: bool = False
    mbpo: MBPOSettings | None = None

    @property
    def agent(self) -> PPOSettings | SACSettings:
        """The agent's group (``ppo`` or ``sac``, by the method)."""
        return self.ppo if self.settings.family == "ppo" else self.sac

    @classmethod
    def from_config(cls, cfg: DictConfig) -> TrainConfig:
        """Validates ``cfg`` and parses it.

        Args:
            cfg: the composed training config.

        Raises:
            ConfigError: naming the first invalid key.
        """
        settings = TrainSettings.from_config(cfg)  # validates
        groups = {name: kind.parse(cfg[name]) for name, kind in GROUPS.items() if name in cfg}
        reward_kwargs = _plain(cfg.reward.get("kwargs")) or {}
        return cls(
            method=settings.method,
            seed=settings.seed,
            total_steps=settings.total_steps,
            planning_updates=int(cfg.planning_updates),
            eval_every=int(cfg.eval_every),
            eval_episodes=settings.eval_episodes,
            progress=bool(cfg.progress),
            env=EnvSettings(str(cfg.env.id), int(cfg.env.num_envs), str(cfg.env.device)),
            reward=RewardSettings(str(cfg.reward.name), dict(reward_kwargs)),
            checkpoint=CheckpointSettings(settings.checkpoint_every, settings.keep_last),
            settings=settings,
            record=flatten_config(cfg),
            restart=bool(cfg.get("restart", False)),
            **groups,  # type: ignore[arg-type]
        )
