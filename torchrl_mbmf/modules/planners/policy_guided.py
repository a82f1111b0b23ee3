"""Policy-guided MPC: candidate actions sampled from the PPO/SAC policy (thesis section 5.3)."""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.envs.model_based import ModelBasedEnvBase

from torchrl_mbmf.modules.planners.common import ShootingPlanner


class PolicyGuidedMPCPlanner(ShootingPlanner):
    """MPC whose candidate trajectories are sampled from a stochastic policy (thesis' PPO-MPC).

    From each real state, ``m`` trajectories of ``h`` steps are imagined in the learned model;
    at every imagined step each candidate's action is sampled from the actor's distribution at
    the candidate's predicted observation (thesis figure 7). The first action of the candidate
    with the highest predicted return (optionally plus a discounted terminal value) is executed
    in the real env. Sampling is always random, also when the caller runs under
    ``ExplorationType.DETERMINISTIC`` (otherwise all candidates would collapse onto the mode).

    The planner writes the executed action and, evaluated at the real state, the actor's
    ``loc``/``scale`` and the action's log-probability (``action_log_prob``): batches collected
    with it feed :class:`~torchrl.objectives.ClipPPOLoss` (and a replay buffer for
    :class:`~torchrl.objectives.SACLoss`) unchanged. Note the off-policy bias this implies, as
    in the thesis: the executed action is the best of ``m`` policy samples, not a plain sample,
    so PPO's importance ratios and advantages are computed for a distribution that is sharper
    than the policy's; only real transitions train the policy.

    Args:
        env: the learned env (a :class:`~torchrl_mbmf.envs.LearnedDynamicsEnv` takes the fast
            tensor path; any other ``ModelBasedEnvBase`` goes through ``env.rollout``).
        actor: the stochastic actor (a ``ProbabilisticActor`` whose distribution has
            ``log_prob``), reading the policy observation.

    Keyword Args:
        num_candidates: candidate trajectories ``m``. Defaults to ``15``.
        horizon: imagined steps ``h``. Defaults to ``10``.
        value_module: module writing ``value_key`` (e.g. the PPO critic); its value at the last
            imagined state is added to the score. Defaults to none (thesis).
        value_key: output key of ``value_module``. Defaults to ``"state_value"``.
        discount: discount of the score. Defaults to ``1.0``.
        action_key: action key. Defaults to ``"action"``.
        log_prob_key: log-prob key. Defaults to ``"action_log_prob"``.
        stats_key: key of the candidates' best/mean predicted return. Defaults to ``"planner"``.

    Examples:
        >>> from torchrl_mbmf.envs import LearnedDynamicsEnv, make_gym_state_env
        >>> from torchrl_mbmf.modules import (DeltaDynamicsModel, PolicyGuidedMPCPlanner,
        ...                                   make_ppo_actor_critic)
        >>> real = make_gym_state_env("Pendulum-v1", seed=0)
        >>> actor, critic = make_ppo_actor_critic(real, hidden_sizes=(16, 16))
        >>> model_env = LearnedDynamicsEnv(DeltaDynamicsModel(3, 1, hidden_sizes=(16,)), real)
        >>> planner = PolicyGuidedMPCPlanner(model_env, actor, num_candidates=15, horizon=10)
        >>> td = real.rollout(3, planner)
        >>> sorted(k for k in ("action", "action_log_prob", "loc", "scale") if k in td.keys())
        ['action', 'action_log_prob', 'loc', 'scale']
    """

    def __init__(
        self,
        env: ModelBasedEnvBase,
        actor: TensorDictModuleBase,
        *,
        num_candidates: int = 15,
        horizon: int = 10,
        value_module: TensorDictModuleBase | None = None,
        value_key: NestedKey = "state_value",
        discount: float = 1.0,
        action_key: NestedKey = "action",
        log_prob_key: NestedKey = "action_log_prob",
        stats_key: NestedKey | None = "planner",
    ) -> None:
        if actor is None:
            raise TypeError("PolicyGuidedMPCPlanner needs a stochastic actor, got None")
        super().__init__(
            env,
            num_candidates=num_candidates,
            horizon=horizon,
            actor=actor,
            value_module=value_module,
            value_key=value_key,
            discount=discount,
            action_key=action_key,
            log_prob_key=log_prob_key,
            stats_key=stats_key,
        )

    def sample_candidate_actions(self, observation: torch.Tensor, step: int) -> torch.Tensor:
        """Actions sampled from the actor at each candidate's observation."""
        return self.sampler.sample(observation)
