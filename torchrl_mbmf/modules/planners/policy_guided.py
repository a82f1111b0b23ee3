"""Policy-guided MPC: candidate actions sampled from the PPO/SAC policy (thesis section 5.3)."""

from __future__ import annotations

from typing import Any

import torch
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.model_based import ModelBasedEnvBase

from torchrl_mbmf.checks import check_number
from torchrl_mbmf.modules.planners.common import ShootingPlanner
from torchrl_mbmf.modules.planners.fast_model import CachedModelStep
from torchrl_mbmf.modules.planners.policy_rollout import PolicyRollout
from torchrl_mbmf.modules.planners.rollout import ImaginedRollout

REFINEMENTS = (None, "cem", "mppi")


class PolicyGuidedMPCPlanner(ShootingPlanner):
    """MPC whose candidate trajectories are sampled from a stochastic policy (thesis' PPO-MPC).

    From each real state, ``m`` trajectories of ``h`` steps are imagined in the learned model;
    at every imagined step each candidate's action is sampled from the actor's distribution at
    the candidate's predicted observation (thesis figure 7). The first action of the candidate
    with the highest predicted return (optionally plus a discounted terminal value) is executed
    in the real env. Sampling is always random, also when the caller runs under
    ``ExplorationType.DETERMINISTIC`` (otherwise all candidates would collapse onto the mode).

    The planner writes the executed action and, evaluated at the real state, the actor's
    ``loc``/``scale`` and the action's log-probability (under the actor's ``log_prob_key``,
    ``action_log_prob`` by default): batches collected
    with it feed :class:`~torchrl.objectives.ClipPPOLoss` (and a replay buffer for
    :class:`~torchrl.objectives.SACLoss`) unchanged. Note the off-policy bias this implies, as
    in the thesis: the executed action is the best of ``m`` policy samples, not a plain sample,
    so PPO's importance ratios and advantages are computed for a distribution that is sharper
    than the policy's; only real transitions train the policy.

    With a :class:`~torchrl_mbmf.envs.LearnedDynamicsEnv` and no refinement, the candidates
    roll out in one fused tensor loop
    (:class:`~torchrl_mbmf.modules.planners.PolicyRollout`) whose candidates,
    returns and chosen action are bit-identical to the step-by-step loop
    (``planner.fused_rollout = False``), drawing the same random numbers.

    Args:
        env: the learned env (a :class:`~torchrl_mbmf.envs.LearnedDynamicsEnv` takes the fast
            tensor path; any other ``ModelBasedEnvBase`` goes through ``env.rollout``).
        actor: the stochastic actor (a ``ProbabilisticActor`` whose distribution has
            ``log_prob``), reading the policy observation.

    Keyword Args:
        refinement: ``None`` (the thesis: one round of policy samples), ``"cem"`` or
            ``"mppi"``: after the policy-sampled round, ``iterations`` more rounds refine a
            Gaussian over action sequences ``[h, action_dim]`` fitted to the previous round
            (CEM: mean and std of its ``num_elites`` best candidates; MPPI: weights
            ``softmax((R - max R) / (temperature * std R))``, so ``temperature`` is unitless).
            In every refined round ``round(policy_fraction * m)`` candidates stay closed-loop
            policy samples and the rest are open-loop sequences drawn from the Gaussian
            (clipped to the action bounds). The executed action is the first action of the
            best candidate over all rounds; its log-prob under the policy is written as
            without refinement. Needs a :class:`~torchrl_mbmf.envs.LearnedDynamicsEnv`.
            Defaults to ``None``.
        iterations: refined rounds after the policy round. Defaults to ``2``.
        num_elites: CEM elites. Defaults to ``3``.
        policy_fraction: share of each refined round's candidates drawn from the policy.
            Defaults to ``1/3``.
        temperature: MPPI temperature (in units of the round's return std). Defaults to ``1.0``.
        min_std: floor of the refined Gaussian's std (action units). Defaults to ``0.05``.
        **kwargs: the keyword arguments of
            :class:`~torchrl_mbmf.modules.planners.ShootingPlanner`, with its defaults:
            ``num_candidates`` (``m = 15``), ``horizon`` (``h = 10``), ``value_module``
            (none: the thesis), ``value_key``, ``discount`` (``1.0``), ``action_key``,
            ``log_prob_key`` and ``stats_key`` (``"planner"``).

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
        refinement: str | None = None,
        iterations: int = 2,
        num_elites: int = 3,
        policy_fraction: float = 1 / 3,
        temperature: float = 1.0,
        min_std: float = 0.05,
        **kwargs: Any,
    ) -> None:
        if actor is None:
            raise TypeError("PolicyGuidedMPCPlanner needs a stochastic actor, got None")
        if refinement not in REFINEMENTS:
            raise ValueError(
                f"refinement={refinement!r} is not supported; allowed: {list(REFINEMENTS)}"
            )
        super().__init__(env, actor=actor, **kwargs)
        num_candidates = self.num_candidates
        self.refinement = refinement
        if refinement is not None:
            if not self.fast_path:
                raise ValueError(
                    f"refinement={refinement!r} needs a LearnedDynamicsEnv, got "
                    f"{type(env).__name__}"
                )
            if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 1:
                raise ValueError(f"iterations must be an integer >= 1, got {iterations!r}")
            elites = isinstance(num_elites, int) and not isinstance(num_elites, bool)
            if not elites or not 1 <= num_elites <= num_candidates:
                raise ValueError(
                    f"num_elites must be an integer in [1, num_candidates={num_candidates}], "
                    f"got {num_elites!r}"
                )
            check_number(policy_fraction, "policy_fraction", minimum=0)
            if not policy_fraction < 1.0:
                raise ValueError(f"policy_fraction must be in [0, 1), got {policy_fraction}")
            check_number(temperature, "temperature", minimum=0)
            if temperature == 0:
                raise ValueError(f"temperature must be > 0, got {temperature}")
            check_number(min_std, "min_std", minimum=0)
        self.iterations = int(iterations)
        self.num_elites = int(num_elites)
        self.num_policy = round(policy_fraction * num_candidates)
        self.temperature = float(temperature)
        self.min_std = float(min_std)
        self.refinement_rounds = self.iterations if refinement is not None else 0
        if self.fast_path and refinement is None and self._samples_the_actor():
            observation = self.env.observation
            self.policy_rollout = PolicyRollout(self._model_step, self.sampler, observation)

    def _samples_the_actor(self) -> bool:
        """Whether candidates are the stock policy samples (subclasses may draw otherwise)."""
        cls = type(self)
        return (
            cls.sample_candidate_actions is PolicyGuidedMPCPlanner.sample_candidate_actions
            and cls.observation_of is ShootingPlanner.observation_of
            and cls.rollout is ShootingPlanner.rollout
            and cls.candidate_source is ShootingPlanner.candidate_source
            and cls.transition is ShootingPlanner.transition
            and cls.horizon_mask is ShootingPlanner.horizon_mask
            and type(self._model_step) is CachedModelStep
        )

    def sample_candidate_actions(self, observation: torch.Tensor, step: int) -> torch.Tensor:
        """Actions sampled from the actor at each candidate's observation."""
        return self.sampler.sample(observation)

    # ------------------------------------------------------------------ refinement
    def _refit(self, actions: torch.Tensor, returns: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Mean and std ``[*B, h, A]`` of the refined Gaussian from one round's candidates."""
        if self.refinement == "cem":
            elite = returns.topk(self.num_elites, dim=-1).indices
            idx = elite[..., None, None].expand(*elite.shape, *actions.shape[-2:])
            chosen = actions.gather(-3, idx)
            mean = chosen.mean(-3)
            std = chosen.std(-3, unbiased=False)
        else:  # mppi
            scale = self.temperature * returns.std(-1, keepdim=True).clamp_min(1e-6)
            w = torch.softmax((returns - returns.amax(-1, keepdim=True)) / scale, dim=-1)
            w = w[..., None, None]
            mean = (w * actions).sum(-3)
            std = (w * (actions - mean.unsqueeze(-3)).pow(2)).sum(-3).sqrt()
        return mean, std.clamp_min(self.min_std)

    def refined_sequences(self, rollout: ImaginedRollout, returns: torch.Tensor) -> torch.Tensor:
        """The next round's open-loop sequences ``[*B, m - round(policy_fraction * m), h, A]``.

        Drawn from the Gaussian refitted to the previous round (CEM or MPPI, see the class
        docstring) and clipped to the action bounds.

        Args:
            rollout: the previous round (with its actions).
            returns: its scores ``[*B, m]``.
        """
        mean, std = self._refit(rollout.actions, returns)
        n_seq = self.num_candidates - self.num_policy
        noise = torch.randn(
            *mean.shape[:-2], n_seq, *mean.shape[-2:], dtype=mean.dtype, device=mean.device
        )
        seqs = mean.unsqueeze(-3) + std.unsqueeze(-3) * noise
        return torch.maximum(torch.minimum(seqs, self.action_high), self.action_low)
