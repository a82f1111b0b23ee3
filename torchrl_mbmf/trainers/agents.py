"""The learning agents of the loop: PPO and SAC, each owning its networks, loss and optimiser.

The agents' interface and their updates: ``docs/design/loop.md``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Protocol, runtime_checkable

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase
from tensordict.nn import AddStateIndependentNormalScale, TensorDictModuleBase
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import EnvBase
from torchrl.objectives import ClipPPOLoss, SACLoss, SoftUpdate
from torchrl.objectives.value import GAE

from torchrl_mbmf.checks import Setting, check_arguments, choice, settings
from torchrl_mbmf.data.mixed_replay import MixedReplaySampler
from torchrl_mbmf.data.replay import ReplaySampler
from torchrl_mbmf.modules.actors import make_ppo_actor_critic, make_sac_actor_critic
from torchrl_mbmf.modules.log_std import SAC_SCALES
from torchrl_mbmf.modules.planners import MinQValue
from torchrl_mbmf.objectives.fused_ppo import FusedPPOUpdate, ppo_update
from torchrl_mbmf.objectives.fused_sac import FusedSACUpdate, sac_update_step
from torchrl_mbmf.trainers.components import instantiate_group
from torchrl_mbmf.trainers.settings import GroupSettings

__all__ = [
    "DISTRIBUTIONS",
    "PPO_UPDATES",
    "SAC_Q_DISTANCES",
    "SAC_UPDATES",
    "Agent",
    "PPOAgent",
    "SACAgent",
    "make_agent",
]

#: PPO policy distributions (``ppo.distribution``).
DISTRIBUTIONS: tuple[str, ...] = ("tanh_normal", "normal")
#: PPO update paths (``ppo.update``).
PPO_UPDATES: tuple[str, ...] = ("fused", "fused_autograd", "stock")
#: SAC update paths (``sac.update``).
SAC_UPDATES: tuple[str, ...] = ("fused", "stock")
#: ``sac.loss_function`` values: ``SACLoss``'s Q distances, both reproduced by the fused update.
SAC_Q_DISTANCES: tuple[str, ...] = ("smooth_l1", "l2")


@runtime_checkable
class Agent(Protocol):
    """What the loop needs of a learning agent: act, learn, and the state a checkpoint holds.

    Args:
        *args: none (a protocol is not instantiated).
        **kwargs: none.

    Attributes:
        actor: the policy that acts on the real env (and guides the planner).
        loss: the TorchRL loss module (its ``in_keys`` are the replay entries).
        replay: the replay buffer, or ``None`` for an on-policy agent.
        logs_update_count: whether the loop logs the update count (PPO: one per batch).

    Examples:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_mbmf.envs import make_env
        >>> cfg = OmegaConf.create({"ppo": OmegaConf.load("configs/algo/ppo.yaml")})
        >>> agent = make_agent("ppo", make_env("Pendulum-v1"), cfg, torch.device("cpu"))
        >>> isinstance(agent, Agent)
        True
    """

    actor: TensorDictModuleBase
    loss: torch.nn.Module
    replay: TensorDictReplayBuffer | None
    logs_update_count: bool

    def observe(self, batch: TensorDictBase) -> None:
        """Keeps the data of a batch that takes no update (the random-data phase)."""

    def update(self, batch: TensorDictBase, real_steps: int) -> dict[str, float] | None:
        """Learns from one collected batch; the scalars to log, ``None`` if it took none."""

    def log_std(self, batch: TensorDictBase | None = None) -> float | None:
        """The policy's mean log-std, for the logs."""

    def checkpoint_components(self) -> dict[str, Any]:
        """The stateful parts a checkpoint holds (tensor state), by name."""

    def terminal_value(self) -> TensorDictModuleBase:
        """The value module a planner may add at its horizon."""


class PPOAgent:
    """Thesis PPO: stock :class:`~torchrl.objectives.ClipPPOLoss` with GAE, Adam (``ppo`` group).

    Args:
        env: the training env (sizes the networks).
        device: device of the networks and updates.

    Keyword Args:
        frames_per_batch: real steps per update (the collector's batch).
        minibatch_size: minibatch size of the PPO epochs.
        epochs: passes over each batch.
        clip_epsilon: PPO's clip range.
        entropy_coeff: weight of the entropy bonus.
        critic_coeff: weight of the value loss.
        gamma: discount.
        lmbda: GAE's lambda.
        lr: Adam's learning rate.
        max_grad_norm: gradient-norm clip.
        hidden_sizes: hidden layers of the actor and critic.
        distribution: ``"normal"`` or ``"tanh_normal"``.
        init_log_std: initial log-std of the policy.
        update: ``"fused"``, ``"fused_autograd"`` or ``"stock"``. Defaults to ``"stock"``.

    Examples:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_mbmf.envs import make_env
        >>> from torchrl_mbmf.trainers.agents import make_agent
        >>> cfg = OmegaConf.create({"ppo": OmegaConf.load("configs/algo/ppo.yaml")})
        >>> agent = make_agent("ppo", make_env("Pendulum-v1", seed=0), cfg, torch.device("cpu"))
        >>> agent.log_std()
        0.0
    """

    #: Whether each update's count is logged as ``train/updates``.
    logs_update_count = True
    #: The range of each argument, checked by the constructor.
    ARGUMENTS: dict[str, Setting] = settings(
        positive_int=("frames_per_batch", "minibatch_size", "epochs"),
        unit=("clip_epsilon", "gamma"),
        non_negative=("entropy_coeff", "critic_coeff"),
        probability=("lmbda",),
        positive=("lr", "max_grad_norm"),
        sizes=("hidden_sizes",),
        finite=("init_log_std",),
    ) | {"distribution": choice(*DISTRIBUTIONS), "update": choice(*PPO_UPDATES)}

    def __init__(
        self,
        env: EnvBase,
        device: torch.device,
        *,
        frames_per_batch: int,
        minibatch_size: int,
        epochs: int,
        clip_epsilon: float,
        entropy_coeff: float,
        critic_coeff: float,
        gamma: float,
        lmbda: float,
        lr: float,
        max_grad_norm: float,
        hidden_sizes: Sequence[int],
        distribution: str,
        init_log_std: float,
        update: str = "stock",
    ) -> None:
        check_arguments(self.ARGUMENTS, locals())
        self.frames_per_batch = frames_per_batch
        self.epochs, self.minibatch_size = int(epochs), int(minibatch_size)
        self.max_grad_norm = float(max_grad_norm)
        self.device = device
        self.actor, self.critic = make_ppo_actor_critic(
            env,
            hidden_sizes=tuple(hidden_sizes),
            distribution=distribution,
            init_log_std=float(init_log_std),
        )
        self.actor.to(device)
        self.critic.to(device)
        self.loss = ClipPPOLoss(
            self.actor,
            self.critic,
            clip_epsilon=float(clip_epsilon),
            entropy_coeff=float(entropy_coeff),
            critic_coeff=float(critic_coeff),
            normalize_advantage=True,
        )
        self.gae = GAE(
            gamma=float(gamma),
            lmbda=float(lmbda),
            value_network=self.critic,
            average_gae=False,
        )
        self.optim = torch.optim.Adam(self.loss.parameters(), lr=float(lr))
        self.replay = None
        self.fused = None
        if update != "stock":
            self.fused = FusedPPOUpdate(
                self.loss,
                self.gae,
                self.optim,
                epochs=self.epochs,
                minibatch_size=self.minibatch_size,
                max_grad_norm=self.max_grad_norm,
                gradients="manual" if update == "fused" else "autograd",
            )
        self._scale = next(
            m for m in self.actor.modules() if isinstance(m, AddStateIndependentNormalScale)
        )

    def log_std(self, batch: TensorDictBase | None = None) -> float:
        """The mean of the policy's state-independent log-std parameter (``batch`` unused)."""
        return float(self._scale.state_independent_scale.detach().mean())

    def observe(self, batch: TensorDictBase) -> None:
        """PPO keeps no data between batches (for the random-data phase; does nothing)."""

    def update(self, batch: TensorDictBase, real_steps: int) -> dict[str, float] | None:
        """One PPO iteration on ``batch``; returns the mean loss entries as ``loss/*``.

        Args:
            batch: a collector batch ``[*B, T]`` with ``action_log_prob``.
            real_steps: real env steps so far (unused: every PPO batch takes an update).
        """
        if self.device.type != "cpu":
            batch = batch.to(self.device)
        if self.fused is not None:
            stats = self.fused(batch)
        else:
            stats = ppo_update(
                self.loss,
                self.gae,
                self.optim,
                batch,
                epochs=self.epochs,
                minibatch_size=self.minibatch_size,
                max_grad_norm=self.max_grad_norm,
            )
        return {f"loss/{k}": v for k, v in stats.items()}

    def checkpoint_components(self) -> dict[str, Any]:
        """The stateful parts a checkpoint holds (tensor state)."""
        return {"loss": self.loss, "optim": self.optim}

    def terminal_value(self) -> TensorDictModuleBase:
        """The planner's terminal value: the critic ``V(s)`` (trained by this loss)."""
        return self.critic


class SACAgent:
    """Standard SAC: stock :class:`~torchrl.objectives.SACLoss`, replay, soft targets (``sac``).

    Args:
        env: the training env (sizes the networks and the action bounds).
        device: device of the networks, replay buffer and updates.

    Keyword Args:
        frames_per_batch: real steps per collected batch.
        utd_ratio: updates per collected frame.
        batch_size: replay minibatch size.
        init_random_frames: frames before the first update.
        replay_size: replay buffer capacity.
        hidden_sizes: hidden layers of the actor and the Q networks.
        lr: Adam's learning rate.
        gamma: discount.
        tau: soft target update rate.
        alpha_init: initial entropy coefficient.
        loss_function: ``SACLoss``'s Q-regression distance, ``"l2"`` (SAC's paper, SB3) or
            ``"smooth_l1"`` (torchrl's default). Defaults to ``"smooth_l1"``.
        scale: the actor's scale parameterisation
            (:func:`~torchrl_mbmf.modules.log_std.make_sac_head`): ``"biased_softplus"``
            (torchrl's default) or ``"clamped_log_std"`` (SAC's reference code,
            Stable-Baselines3). Defaults to ``"biased_softplus"``.
        refit_every_steps: ``sac_mpc``'s world-model refit period in real steps (read by the
            :class:`~torchrl_mbmf.trainers.schedule.PhaseSchedule`).
        update: ``"fused"`` or ``"stock"``. Defaults to ``"stock"``.

    Examples:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_mbmf.envs import make_env
        >>> from torchrl_mbmf.trainers.agents import make_agent
        >>> env = make_env("Pendulum-v1", seed=0)
        >>> cfg = OmegaConf.create({"sac": OmegaConf.load("configs/algo/sac.yaml")})
        >>> agent = make_agent("sac", env, cfg, torch.device("cpu"))
        >>> batch = env.rollout(100, agent.actor)
        >>> agent.update(batch, real_steps=100) is None  # within sac.init_random_frames
        True
        >>> len(agent.replay)
        100
    """

    logs_update_count = False
    #: The range of each argument, checked by the constructor.
    ARGUMENTS: dict[str, Setting] = settings(
        positive_int=("frames_per_batch", "batch_size", "replay_size", "refit_every_steps"),
        count=("init_random_frames",),
        positive=("utd_ratio", "lr", "alpha_init"),
        unit=("gamma", "tau"),
        sizes=("hidden_sizes",),
    ) | {
        "update": choice(*SAC_UPDATES),
        "loss_function": choice(*SAC_Q_DISTANCES),
        "scale": choice(*SAC_SCALES),
    }

    def __init__(
        self,
        env: EnvBase,
        device: torch.device,
        *,
        frames_per_batch: int,
        utd_ratio: float,
        batch_size: int,
        init_random_frames: int,
        replay_size: int,
        hidden_sizes: Sequence[int],
        lr: float,
        gamma: float,
        tau: float,
        alpha_init: float,
        refit_every_steps: int,
        update: str = "stock",
        loss_function: str = "smooth_l1",
        scale: str = "biased_softplus",
    ) -> None:
        check_arguments(self.ARGUMENTS, locals())
        self.frames_per_batch, self.refit_every_steps = frames_per_batch, refit_every_steps
        self.init_random_frames, self.utd_ratio = int(init_random_frames), float(utd_ratio)
        self.device = device
        self.actor, self.critic = make_sac_actor_critic(
            env, hidden_sizes=tuple(hidden_sizes), scale=scale
        )
        self.actor.to(device)
        self.critic.to(device)
        self.loss = SACLoss(
            self.actor,
            self.critic,
            num_qvalue_nets=2,
            alpha_init=float(alpha_init),
            loss_function=loss_function,
            action_spec=env.full_action_spec_unbatched[env.action_key],
        )
        self.loss.to(device)
        self.loss.make_value_estimator(gamma=float(gamma))
        self.target_updater = SoftUpdate(self.loss, tau=float(tau))
        fused = update == "fused"
        # the fused path also uses torch's fused Adam (same update up to float rounding)
        self.optim = torch.optim.Adam(self.loss.parameters(), lr=float(lr), fused=fused)
        self.replay = TensorDictReplayBuffer(
            storage=LazyTensorStorage(int(replay_size), device=device),
            batch_size=int(batch_size),
        )
        self.sampler: ReplaySampler | MixedReplaySampler | None = None
        self.sample = self.replay.sample
        if fused:
            self.step = FusedSACUpdate(self.loss, self.optim, self.target_updater)
            self.sampler = ReplaySampler(self.replay, self.step.batch_keys)
        else:
            self.step = sac_update_step(self.loss, self.optim, self.target_updater)

    def log_std(self, batch: TensorDictBase | None = None) -> float | None:
        """The mean log-std of the actor's actions in ``batch`` (``None`` without a scale)."""
        scale = None if batch is None else batch.get("scale", None)
        return None if scale is None else float(scale.log().mean())

    def observe(self, batch: TensorDictBase) -> None:
        """Stores ``batch`` in the replay buffer: the entries ``SACLoss`` reads, flattened."""
        self.replay.extend(batch.reshape(-1).select(*self.loss.in_keys, strict=False))

    def update(self, batch: TensorDictBase, real_steps: int) -> dict[str, float] | None:
        """Stores ``batch``, then ``utd_ratio`` updates per frame past ``init_random_frames``.

        Args:
            batch: a collector batch.
            real_steps: real env steps so far, ``batch`` included.

        Returns:
            The mean of each loss entry over the updates as ``loss/*``, or ``None`` when the
            batch takes no update.
        """
        self.observe(batch)
        past = real_steps - max(self.init_random_frames, real_steps - batch.numel())
        updates = round(past * self.utd_ratio)
        if updates <= 0:
            return None
        stats: dict[str, list[torch.Tensor]] = {}
        for _ in range(updates):
            if self.sampler is not None:
                out = self.step.update(*self.sampler())
            else:
                out = self.step(self.sample())
            for k, v in out.items():
                stats.setdefault(k, []).append(torch.as_tensor(v).detach())
        return {f"loss/{k}": float(torch.stack(v).float().mean()) for k, v in stats.items()}

    def mix_model_replay(self, model: TensorDictReplayBuffer, real_ratio: float) -> None:
        """Draws every update batch as ``real_ratio`` real and the rest ``model`` rows (MBPO).

        Args:
            model: the model replay (the entries of :attr:`replay`).
            real_ratio: the real share of a batch, in ``[0, 1]``.
        """
        size = self.replay.batch_size
        if self.sampler is not None:
            keys = self.step.batch_keys
            self.sampler = MixedReplaySampler(self.replay, model, keys, size, real_ratio)
        mixed = MixedReplaySampler(self.replay, model, self.loss.in_keys, size, real_ratio)
        self.sample = mixed.sample

    def checkpoint_components(self) -> dict[str, Any]:
        """The stateful parts a checkpoint holds as tensor state (the replay buffer apart)."""
        return {"loss": self.loss, "optim": self.optim}

    def terminal_value(self) -> TensorDictModuleBase:
        """The planner's terminal value: ``min_i Q_i`` at the actor's action."""
        return MinQValue(self.actor, self.critic, self.loss.qvalue_network_params)


def make_agent(
    method_family: str,
    env: EnvBase,
    cfg: DictConfig | GroupSettings,
    device: torch.device,
) -> Agent:
    """The agent of ``method_family`` (``"ppo"`` or ``"sac"``) built from its group's settings.

    Args:
        method_family: ``"ppo"`` or ``"sac"``.
        env: the training env.
        cfg: the group's parsed settings
            (:class:`~torchrl_mbmf.trainers.settings.PPOSettings` /
            :class:`~torchrl_mbmf.trainers.settings.SACSettings`), or a training config whose
            ``method_family`` group is read.
        device: device of the networks and updates.

    Raises:
        ConfigError: naming the key of an argument the agent refuses (``ppo.gamma``).

    Examples:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_mbmf.envs import make_env
        >>> from torchrl_mbmf.trainers.agents import make_agent
        >>> cfg = OmegaConf.create({"sac": OmegaConf.load("configs/algo/sac.yaml")})
        >>> type(make_agent("sac", make_env("Pendulum-v1"), cfg, torch.device("cpu"))).__name__
        'SACAgent'
    """
    if method_family not in ("ppo", "sac"):
        raise ValueError(f"method_family={method_family!r}; expected one of ['ppo', 'sac']")
    if isinstance(cfg, GroupSettings):
        agent = cfg.build(env=env, device=device)
    else:
        agent = instantiate_group(cfg, method_family, env=env, device=device)
    if not isinstance(agent, Agent):
        raise TypeError(
            f"{method_family}._target_ built a {type(agent).__name__}, which is no Agent "
            f"(it needs {sorted(n for n in dir(Agent) if not n.startswith('_'))})"
        )
    return agent
