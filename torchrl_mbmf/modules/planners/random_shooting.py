"""Naive MPC: random shooting with uniformly sampled actions (thesis section 2.1.3)."""

from __future__ import annotations

import torch

from torchrl_mbmf.modules.planners.common import ShootingPlanner


class RandomShootingMPCPlanner(ShootingPlanner):
    """Random-shooting MPC: every candidate action is drawn from ``U(low, high)`` of the spec.

    The thesis' "MPC" baseline (Nagabandi et al. 2018): ``m`` uniformly random action
    sequences of length ``h`` are rolled out in the learned model and the first action of the
    highest-return one is executed. Given an ``actor``, the planner also writes that actor's
    ``loc``/``scale`` at the real state and the log-prob of the executed action, so PPO can be
    trained on these transitions as in the thesis' MPC variant. PPO then learns from actions it
    did not choose: the importance ratio starts from the actor's density of an action drawn
    uniformly and filtered by the planner, an off-policy bias the thesis accepts.

    Args:
        env: the learned env (a :class:`~torchrl_mbmf.envs.LearnedDynamicsEnv` takes the fast
            tensor path; any other ``ModelBasedEnvBase`` goes through ``env.rollout``).

    Keyword Args:
        num_candidates: candidate trajectories ``m``. Defaults to ``15``.
        horizon: imagined steps ``h``. Defaults to ``10``.
        actor: stochastic actor whose log-prob of the chosen action is written. Defaults to none.
        value_module: module adding a terminal value to the score. Defaults to none.
        value_key: output key of ``value_module``. Defaults to ``"state_value"``.
        discount: discount of the score. Defaults to ``1.0``.
        action_key: action key. Defaults to ``"action"``.
        log_prob_key: log-prob key. Defaults to the actor's ``log_prob_key`` (else
            ``"action_log_prob"``).
        stats_key: key of the candidates' best/mean predicted return. Defaults to ``"planner"``.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.envs import LearnedDynamicsEnv, make_gym_state_env
        >>> from torchrl_mbmf.modules import DeltaDynamicsModel, RandomShootingMPCPlanner
        >>> real = make_gym_state_env("Pendulum-v1", seed=0)
        >>> model_env = LearnedDynamicsEnv(DeltaDynamicsModel(3, 1, hidden_sizes=(16,)), real)
        >>> planner = RandomShootingMPCPlanner(model_env, num_candidates=15, horizon=10)
        >>> td = real.rollout(3, planner)
        >>> td["action"].shape, bool((td["action"].abs() <= 2).all())
        (torch.Size([3, 1]), True)
    """

    def sample_candidate_actions(self, observation: torch.Tensor, step: int) -> torch.Tensor:
        """Uniform actions in the spec's bounds, ``[*B, m, action_dim]``."""
        shape = (*observation.shape[:-1], self.action_dim)
        u = torch.rand(shape, dtype=self.action_low.dtype, device=observation.device)
        return self.action_low + (self.action_high - self.action_low) * u
