"""Stable-Baselines3 reference agents with this package's settings, logging into its run layout.

The thesis' PPO (table 6) and standard SAC as Stable-Baselines3 builds them, from the same
``configs/algo/*.yaml`` settings our trainers read, so that a reference run differs from ours only
by the implementation. :class:`RunFolderCallback` logs what our trainer logs per episode
(``train/episode_return``, ``train/return_last10_mean|min|max``, ``train/episodes``) and per
evaluation (``eval/return``: the deterministic policy on a fresh episode) through a
``torchrl.record`` logger, so ``torchrl_mbmf.analysis`` reads SB3 runs like ours.

Needs the ``bench`` extra (``pip install -e ".[bench]"``); importing this module without
Stable-Baselines3 raises an ``ImportError`` that says so.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from torch import nn
from torchrl.record.loggers import Logger

try:
    from stable_baselines3 import PPO, SAC
    from stable_baselines3.common.base_class import BaseAlgorithm
    from stable_baselines3.common.callbacks import BaseCallback
except ImportError as err:  # pragma: no cover - exercised only without the extra
    raise ImportError(
        "torchrl_mbmf.baselines.sb3 needs Stable-Baselines3: pip install -e '.[bench]'"
    ) from err

__all__ = ["SB3_ALGOS", "RunFolderCallback", "make_sb3_model", "sb3_grad_steps"]

#: The Stable-Baselines3 algorithms with a counterpart here (our ``ppo`` and ``sac`` methods).
SB3_ALGOS = ("ppo", "sac")

_PPO_KEYS = (
    "frames_per_batch",
    "minibatch_size",
    "epochs",
    "lr",
    "gamma",
    "lmbda",
    "clip_epsilon",
    "entropy_coeff",
    "critic_coeff",
    "max_grad_norm",
    "hidden_sizes",
    "init_log_std",
)
_SAC_KEYS = (
    "lr",
    "replay_size",
    "init_random_frames",
    "batch_size",
    "tau",
    "gamma",
    "utd_ratio",
    "alpha_init",
    "hidden_sizes",
)


def make_sb3_model(
    algo: str, env: gym.Env, config: Mapping[str, Any], *, seed: int, device: str = "cpu"
) -> BaseAlgorithm:
    """Builds Stable-Baselines3's PPO or SAC with the settings of ``configs/algo/<algo>.yaml``.

    PPO: ``n_steps = frames_per_batch``, ``batch_size = minibatch_size``, ``n_epochs = epochs``,
    the clip range, GAE lambda, entropy and value coefficients, gradient-norm clip, normalised
    advantages, separate ``hidden_sizes`` ReLU networks for policy and value and the initial
    log-std; SB3 samples a Gaussian and clips it to the bounds (ours, by default: the thesis'
    Gaussian with a tanh-squashed mean, ``ppo.distribution=normal``), and, like ours,
    normalises no observation. SAC: ``learning_starts = init_random_frames`` (uniform
    random actions until then, as ours), ``utd_ratio`` gradient steps per env step, automatic
    entropy tuning from ``alpha_init``, ``hidden_sizes`` ReLU networks.

    Args:
        algo: ``"ppo"`` or ``"sac"``.
        env: a gymnasium env (SB3 wraps it in its ``Monitor`` and ``DummyVecEnv``).
        config: the algorithm's settings (the keys of ``configs/algo/<algo>.yaml``).

    Keyword Args:
        seed: SB3's seed (networks, sampling and the env's first reset).
        device: torch device of the networks. Defaults to ``"cpu"``.

    Returns:
        The untrained SB3 model.

    Raises:
        ValueError: ``algo`` is not one of :data:`SB3_ALGOS`, or a setting is missing.

    Examples:
        >>> import gymnasium as gym
        >>> from torchrl_mbmf.baselines.sb3 import make_sb3_model
        >>> cfg = dict(frames_per_batch=64, minibatch_size=32, epochs=1, lr=3e-4, gamma=0.99,
        ...            lmbda=0.95, clip_epsilon=0.2, entropy_coeff=0.0, critic_coeff=0.5,
        ...            max_grad_norm=0.5, hidden_sizes=[8, 8], init_log_std=0.0)
        >>> model = make_sb3_model("ppo", gym.make("Pendulum-v1"), cfg, seed=0)
        >>> model.n_steps, model.batch_size
        (64, 32)
    """
    if algo not in SB3_ALGOS:
        raise ValueError(
            f"algo={algo!r} has no Stable-Baselines3 reference; expected one of {SB3_ALGOS}"
        )
    needed = _PPO_KEYS if algo == "ppo" else _SAC_KEYS
    missing = [k for k in needed if k not in config]
    if missing:
        raise ValueError(f"the {algo} settings lack {missing}; expected every key of {needed}")
    c = config
    hidden = [int(h) for h in c["hidden_sizes"]]
    if algo == "ppo":
        return PPO(
            "MlpPolicy",
            env,
            n_steps=int(c["frames_per_batch"]),
            batch_size=int(c["minibatch_size"]),
            n_epochs=int(c["epochs"]),
            learning_rate=float(c["lr"]),
            gamma=float(c["gamma"]),
            gae_lambda=float(c["lmbda"]),
            clip_range=float(c["clip_epsilon"]),
            ent_coef=float(c["entropy_coeff"]),
            vf_coef=float(c["critic_coeff"]),
            max_grad_norm=float(c["max_grad_norm"]),
            normalize_advantage=True,
            policy_kwargs={
                "net_arch": {"pi": hidden, "vf": hidden},
                "activation_fn": nn.ReLU,
                "log_std_init": float(c["init_log_std"]),
            },
            seed=int(seed),
            device=device,
            verbose=0,
        )
    return SAC(
        "MlpPolicy",
        env,
        learning_rate=float(c["lr"]),
        buffer_size=int(c["replay_size"]),
        learning_starts=int(c["init_random_frames"]),
        batch_size=int(c["batch_size"]),
        tau=float(c["tau"]),
        gamma=float(c["gamma"]),
        train_freq=1,
        gradient_steps=max(1, int(float(c["utd_ratio"]))),
        ent_coef=f"auto_{float(c['alpha_init'])}",
        policy_kwargs={"net_arch": hidden, "activation_fn": nn.ReLU},
        seed=int(seed),
        device=device,
        verbose=0,
    )


def sb3_grad_steps(model: BaseAlgorithm) -> int:
    """Gradient steps a trained SB3 PPO or SAC model took.

    SB3's PPO counts epochs in ``_n_updates``; each epoch is ``ceil(n_steps / batch_size)``
    minibatch steps. SAC counts gradient steps directly.

    Args:
        model: a Stable-Baselines3 ``PPO`` or ``SAC`` model.

    Examples:
        >>> import gymnasium as gym
        >>> from torchrl_mbmf.baselines.sb3 import make_sb3_model, sb3_grad_steps
        >>> cfg = dict(frames_per_batch=64, minibatch_size=32, epochs=2, lr=3e-4, gamma=0.99,
        ...            lmbda=0.95, clip_epsilon=0.2, entropy_coeff=0.0, critic_coeff=0.5,
        ...            max_grad_norm=0.5, hidden_sizes=[8, 8], init_log_std=0.0)
        >>> model = make_sb3_model("ppo", gym.make("Pendulum-v1"), cfg, seed=0).learn(64)
        >>> sb3_grad_steps(model)
        4
    """
    n_updates = int(getattr(model, "_n_updates", 0))
    if isinstance(model, PPO):
        return n_updates * math.ceil(model.n_steps / model.batch_size)
    return n_updates


class RunFolderCallback(BaseCallback):
    """Logs an SB3 run's episodes and evaluations as this package's trainer logs its own.

    At every episode end: ``train/episode_return`` and, over the last 10 episodes,
    ``train/return_last10_mean``, ``_min``, ``_max``, with ``train/episodes``; every
    ``eval_every`` real steps (first after the first step, as ours after its first batch):
    ``eval/return``, the mean return of ``eval_episodes`` deterministic episodes on
    ``eval_env`` reset with seed ``seed + 1000 + step``. The step of every row is SB3's
    ``num_timesteps`` (every real env step counted).

    Args:
        logger: a ``torchrl.record`` logger (``CSVLogger(exp_name="logs", log_dir=run_dir)``
            writes ``run_dir/logs/scalars/<group>/<name>.csv``, the layout of our runs).
        eval_env: a separate gymnasium env for evaluation.

    Keyword Args:
        seed: the run's seed (evaluation episodes are seeded from it).
        eval_every: real steps between evaluations.
        eval_episodes: episodes per evaluation; ``0`` evaluates never.

    Examples:
        >>> import tempfile
        >>> import gymnasium as gym
        >>> from torchrl.record.loggers import CSVLogger
        >>> from torchrl_mbmf.baselines.sb3 import RunFolderCallback, make_sb3_model
        >>> cfg = dict(frames_per_batch=200, minibatch_size=100, epochs=1, lr=3e-4, gamma=0.99,
        ...            lmbda=0.95, clip_epsilon=0.2, entropy_coeff=0.0, critic_coeff=0.5,
        ...            max_grad_norm=0.5, hidden_sizes=[8, 8], init_log_std=0.0)
        >>> logger = CSVLogger(exp_name="logs", log_dir=tempfile.mkdtemp())
        >>> cb = RunFolderCallback(logger, gym.make("Pendulum-v1"), seed=0, eval_every=400,
        ...                        eval_episodes=1)
        >>> _ = make_sb3_model("ppo", gym.make("Pendulum-v1"), cfg, seed=0).learn(400, callback=cb)
        >>> cb.episodes, len(cb.eval_returns)  # 200-step episodes; evaluated at steps 1 and 400
        (2, 2)
    """

    def __init__(
        self,
        logger: Logger,
        eval_env: gym.Env,
        *,
        seed: int,
        eval_every: int,
        eval_episodes: int,
    ) -> None:
        if eval_every < 1:
            raise ValueError(f"eval_every={eval_every} must be a positive number of steps")
        if eval_episodes < 0:
            raise ValueError(f"eval_episodes={eval_episodes} must be >= 0")
        super().__init__(verbose=0)
        self.run_logger = logger
        self.eval_env = eval_env
        self.seed = int(seed)
        self.eval_every = int(eval_every)
        self.eval_episodes = int(eval_episodes)
        self.episodes = 0
        self.last_returns: deque[float] = deque(maxlen=10)
        self.eval_returns: list[float] = []
        self.next_eval = 0

    def _log(self, metrics: Mapping[str, float], step: int) -> None:
        for name, value in metrics.items():
            value = float(value)
            if not math.isfinite(value):
                raise FloatingPointError(f"{name} = {value} at step {step}: training diverged")
            self.run_logger.log_scalar(name, value, step=step)

    def evaluate(self) -> float:
        """Mean return of ``eval_episodes`` deterministic episodes of the current policy."""
        returns = []
        for i in range(self.eval_episodes):
            obs, _ = self.eval_env.reset(seed=self.seed + 1000 + self.num_timesteps + i)
            total, done = 0.0, False
            while not done:
                action, _ = self.model.predict(obs, deterministic=True)
                obs, reward, terminated, truncated, _ = self.eval_env.step(action)
                total += float(reward)
                done = terminated or truncated
            returns.append(total)
        return float(np.mean(returns))

    def _on_step(self) -> bool:
        step = int(self.num_timesteps)
        for info in self.locals.get("infos", ()):
            episode = info.get("episode")
            if episode is None:
                continue
            self.episodes += 1
            self.last_returns.append(float(episode["r"]))
            self._log({"train/episode_return": float(episode["r"])}, step)
            arr = np.asarray(self.last_returns)
            self._log(
                {
                    "train/return_last10_mean": arr.mean(),
                    "train/return_last10_min": arr.min(),
                    "train/return_last10_max": arr.max(),
                    "train/episodes": self.episodes,
                },
                step,
            )
        if self.eval_episodes and step >= self.next_eval:
            with torch.no_grad():
                value = self.evaluate()
            self.eval_returns.append(value)
            self._log({"eval/return": value}, step)
            while self.next_eval <= step:
                self.next_eval += self.eval_every
        return True
