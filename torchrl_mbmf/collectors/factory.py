"""Collectors of a run: the lean collector where the env supports it, and the evaluation rollout."""

from __future__ import annotations

import copy
from collections.abc import Callable

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.collectors import Collector
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_mbmf.checks import check_finite
from torchrl_mbmf.collectors.lean import LeanCollector

__all__ = ["evaluate_policy", "make_collector"]


def make_collector(
    env: EnvBase,
    policy: TensorDictModuleBase | Callable[[TensorDictBase], TensorDictBase],
    frames: int,
    total: int,
    device: torch.device,
    kind: str = "lean",
) -> Collector | LeanCollector:
    """The lean collector where the env supports it (``kind="lean"``), else the stock one.

    Args:
        env: the (CPU) env.
        policy: the acting policy.
        frames: frames per batch.
        total: total frames (``-1``: unbounded).
        device: the policy's device.
        kind: ``"lean"`` or ``"stock"`` (``collector`` setting).

    Examples:
        >>> from torchrl.envs.utils import RandomPolicy
        >>> from torchrl_mbmf.collectors.factory import make_collector
        >>> from torchrl_mbmf.envs import make_env
        >>> env = make_env("Pendulum-v1", seed=0)
        >>> c = make_collector(env, RandomPolicy(env.full_action_spec), 8, 8, torch.device("cpu"))
        >>> next(iter(c)).numel()
        8
    """
    if kind == "lean" and LeanCollector.supports(env):
        return LeanCollector(
            env, policy, frames_per_batch=frames, total_frames=total, policy_device=device
        )
    devices = {}
    if device.type != "cpu":
        devices = {"policy_device": device, "env_device": "cpu", "storing_device": "cpu"}
    return Collector(
        env,
        policy,
        frames_per_batch=frames,
        total_frames=total,
        auto_register_policy_transforms=False,
        **devices,
    )


def evaluate_policy(
    env: EnvBase,
    actor: TensorDictModuleBase,
    episodes: int,
    device: torch.device,
    kind: str = "lean",
    step: int = 0,
) -> float:
    """Mean return of ``actor`` alone, deterministic, over ``episodes`` episodes of ``env``.

    Args:
        env: the evaluation env (one env; seeded by the caller).
        actor: the policy.
        episodes: episodes to average.
        device: the actor's device.
        kind: the collection path (``"lean"``: the same episode as ``env.rollout``, tested).
        step: the real-step count named if the return is not finite.

    Examples:
        >>> from torchrl_mbmf.collectors.factory import evaluate_policy
        >>> from torchrl_mbmf.envs import make_env
        >>> from torchrl_mbmf.modules import make_ppo_actor_critic
        >>> env = make_env("Pendulum-v1", seed=0)
        >>> actor, _ = make_ppo_actor_critic(env, hidden_sizes=(8,))
        >>> evaluate_policy(env, actor, 1, torch.device("cpu")) < 0
        True
    """
    returns = []
    lean = kind == "lean" and LeanCollector.supports(env)
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        for _ in range(int(episodes)):
            if lean:
                td = LeanCollector(
                    env,
                    actor,
                    frames_per_batch=1,
                    exploration_type=ExplorationType.DETERMINISTIC,
                    policy_device=device,
                ).episode()
            elif device.type != "cpu":
                # the stock env rollout runs the policy where the env is: a CPU copy
                td = env.rollout(100_000, copy.deepcopy(actor).to("cpu"))
            else:
                td = env.rollout(100_000, actor)
            returns.append(float(td.get(("next", "reward")).sum()))
    mean = float(np.mean(returns))
    check_finite({"eval/return": mean}, step)
    return mean
