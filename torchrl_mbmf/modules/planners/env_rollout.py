"""The shooting planners' generic path: candidates rolled out through ``env.rollout``."""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_mbmf.modules.planners.sampling import ActorSampler

if TYPE_CHECKING:
    from torchrl_mbmf.modules.planners.common import ShootingPlanner


def rollout_in_env(
    planner: ShootingPlanner, tensordict: TensorDictBase
) -> tuple[torch.Tensor, torch.Tensor, TensorDictBase, torch.Tensor]:
    """Rolls ``planner``'s candidates out with ``planner.env.rollout`` (any model-based env).

    Each real state of ``tensordict`` (batch ``[*B]``) is expanded to ``m`` candidates and
    rolled ``h`` steps; the actions come from ``planner.sample_candidate_actions``.

    Args:
        planner: the planner (its env, ``num_candidates``, ``horizon``, keys and sampler).
        tensordict: the real states.

    Returns:
        ``(first actions [*B, m, A], rewards [*B, m, h], final entries [*B, m],
        terminated [*B, m, h])``.

    Examples:
        >>> from torchrl_mbmf.envs import LearnedDynamicsEnv, make_gym_state_env
        >>> from torchrl_mbmf.modules import DeltaDynamicsModel, RandomShootingMPCPlanner
        >>> from torchrl_mbmf.modules.planners.env_rollout import rollout_in_env
        >>> real = make_gym_state_env("Pendulum-v1", seed=0)
        >>> env = LearnedDynamicsEnv(DeltaDynamicsModel(3, 1, hidden_sizes=(8,)), real)
        >>> planner = RandomShootingMPCPlanner(env, num_candidates=4, horizon=2)
        >>> first, rewards, final, terminated = rollout_in_env(planner, real.reset())
        >>> first.shape, rewards.shape, terminated.dtype
        (torch.Size([4, 1]), torch.Size([4, 2]), torch.bool)
    """
    env = planner.env
    start = tensordict.select(*planner.in_keys).unsqueeze(-1)
    start = start.expand(*tensordict.batch_size, planner.num_candidates).clone()
    if planner.sampler is not None:
        obs_key = planner.sampler.observation_key
    else:
        obs_key = getattr(env, "observation_key", None) or planner.state_key

    class _CandidateSampler:
        step = 0

        def __call__(self, td: TensorDictBase) -> TensorDictBase:
            actions = planner.sample_candidate_actions(td.get(obs_key), self.step)
            td.set(planner.action_key, actions)
            self.step += 1
            return td

    rollout = env.rollout(
        planner.horizon,
        policy=_CandidateSampler(),
        tensordict=env.reset(start),
        auto_reset=False,
        break_when_any_done=False,
    )
    first = rollout.get(planner.action_key)[..., 0, :]
    rewards = rollout.get(("next", "reward"))[..., 0]
    final = rollout.get("next")[..., -1].select(*planner.in_keys)
    nxt = rollout.get("next")
    key = "terminated" if "terminated" in nxt else "done"
    terminated = nxt.get(key, None)
    if terminated is None:
        terminated = torch.zeros(rewards.shape, dtype=torch.bool, device=rewards.device)
    else:
        terminated = terminated.reshape(rewards.shape).bool()
    return first, rewards, final, terminated


def check_actor_fits(sampler: ActorSampler, env: EnvBase, action_dim: int) -> None:
    """Raises unless ``sampler``'s actor reads an observation of ``env`` and acts in ``A``.

    Args:
        sampler: the actor's sampler.
        env: the learned env.
        action_dim: the env's action size ``A``.

    Raises:
        KeyError: the env does not produce the actor's observation key.
        ValueError: the actor cannot read that observation, or its actions' size is not ``A``.

    Examples:
        >>> from torchrl_mbmf.envs import LearnedDynamicsEnv, make_gym_state_env
        >>> from torchrl_mbmf.modules import DeltaDynamicsModel, make_ppo_actor_critic
        >>> from torchrl_mbmf.modules.planners import ActorSampler
        >>> from torchrl_mbmf.modules.planners.env_rollout import check_actor_fits
        >>> real = make_gym_state_env("Pendulum-v1", seed=0)
        >>> env = LearnedDynamicsEnv(DeltaDynamicsModel(3, 1, hidden_sizes=(8,)), real)
        >>> actor, _ = make_ppo_actor_critic(real, hidden_sizes=(8,))
        >>> check_actor_fits(ActorSampler(actor), env, 1)
    """
    obs_key = sampler.observation_key
    spec = env.full_observation_spec_unbatched
    if obs_key not in spec.keys(True):
        raise KeyError(
            f"the actor reads {obs_key!r}, which the learned env does not produce; it "
            f"produces {sorted(map(str, spec.keys(True, True)))}"
        )
    obs = spec[obs_key].zero()
    try:
        with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
            action = sampler.sample(obs.unsqueeze(0))
    except RuntimeError as err:
        raise ValueError(
            f"the actor cannot read the env's {obs_key!r} of shape {tuple(obs.shape)}: {err}"
        ) from err
    if action.shape[-1] != action_dim:
        raise ValueError(
            f"the actor's actions have size {action.shape[-1]}, the env's action spec "
            f"has size {action_dim}"
        )


__all__ = ["check_actor_fits", "rollout_in_env"]
