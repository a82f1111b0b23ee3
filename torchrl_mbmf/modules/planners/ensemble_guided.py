"""Policy-guided MPC on an ensemble world model, with an uncertainty-adaptive horizon."""

from __future__ import annotations

import numbers
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.envs.model_based import ModelBasedEnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_mbmf.modules.ensemble import EnsembleDeltaDynamicsModel
from torchrl_mbmf.modules.planners.common import (
    Plan,
    discounted_return,
    expand_candidates,
    select_best,
)
from torchrl_mbmf.modules.planners.policy_guided import PolicyGuidedMPCPlanner


@dataclass
class EnsemblePlan(Plan):
    """The outcome of one ensemble planning call (a :class:`Plan` plus the trust record).

    Attributes:
        first_actions: first action of every candidate ``[*B, m, action_dim]``.
        returns: score of every candidate ``[*B, m]``.
        best: index of the chosen candidate ``[*B]``.
        trusted_steps: number of imagined steps counted in every candidate's score ``[*B, m]``
            (the horizon when no threshold is set).
        disagreement: the members' disagreement at every candidate's imagined ``(s, a)``
            ``[*B, m, h]``, or ``None`` when it was not computed.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.modules.planners import EnsemblePlan
        >>> plan = EnsemblePlan(torch.zeros(1, 3, 1), torch.tensor([[0.0, 2.0, 1.0]]),
        ...                     torch.tensor([1]), torch.tensor([[4, 2, 5]]), None)
        >>> plan.effective_horizon
        tensor([2])
    """

    trusted_steps: torch.Tensor
    disagreement: torch.Tensor | None

    @property
    def effective_horizon(self) -> torch.Tensor:
        """Trusted steps of the chosen candidate ``[*B]``."""
        return self.trusted_steps.gather(-1, self.best.unsqueeze(-1)).squeeze(-1)


class EnsemblePolicyGuidedPlanner(PolicyGuidedMPCPlanner):
    """Policy-guided MPC in an ensemble world model, with an uncertainty-adaptive horizon.

    As :class:`~torchrl_mbmf.modules.PolicyGuidedMPCPlanner` (``m`` candidates sampled from the
    actor at every imagined step, best first action executed, its log-prob, ``loc`` and
    ``scale`` written for PPO; the same off-policy bias: PPO sees a best-of-``m`` action), on a
    learned env built on an :class:`~torchrl_mbmf.modules.EnsembleDeltaDynamicsModel` of ``K``
    members. Candidate ``i`` is rolled out in member ``i mod K`` (trajectory sampling, as in
    PETS), so the ``m`` candidates see the spread of the members' predictions.

    **Adaptive horizon.** At each imagined step ``t`` the disagreement ``d_t`` of the members at
    the candidate's ``(s_t, a_t)`` is computed
    (:meth:`~torchrl_mbmf.modules.EnsembleDeltaDynamicsModel.disagreement`). With
    ``disagreement_threshold`` set, a candidate's trusted steps ``T`` end at its first step with
    ``d_t > disagreement_threshold``: that step's reward and all later ones are excluded, and the
    score is ``sum_{t<T} discount^t r_t + discount^T V(s_T)``, the terminal value (with a
    ``value_module``) taken at the last trusted state ``s_T`` (the real state when ``T = 0``).
    Without a value module, truncated candidates simply have fewer reward terms; when the model
    is unsure at the real state itself all scores tie and the first candidate, a plain policy
    sample, runs. With ``disagreement_threshold=None`` every candidate keeps all ``h`` steps:
    the plain policy-guided planner on the ensemble. A threshold can be picked on held-out
    real data with
    :func:`~torchrl_mbmf.trainers.ensemble_fit.calibrate_disagreement_threshold`.

    **Speed.** Each imagined step runs all ``K`` members on all candidates in one batched op
    per layer (``K`` times one model's FLOPs), which the disagreement needs, and keeps each
    candidate's own member's prediction. When neither a threshold nor ``stats_key`` is set, the
    disagreement is not needed and each candidate goes through its own member only (candidates
    grouped ``[*B, m] -> [*B, m/K, K]``, one model's FLOPs); both paths give the same plan.

    Besides ``best_return`` and ``mean_return``, ``stats_key`` receives
    ``effective_horizon`` (the chosen candidate's trusted steps, ``[*B, 1]``) and
    ``disagreement`` (the mean disagreement over all candidates and imagined steps of the
    plan, ``[*B, 1]``).

    Args:
        env: a :class:`~torchrl_mbmf.envs.LearnedDynamicsEnv` (or
            :class:`~torchrl_mbmf.envs.EnsembleLearnedDynamicsEnv`) on an ensemble.
        actor: the stochastic actor (a ``ProbabilisticActor``), reading the policy observation.

    Keyword Args:
        disagreement_threshold: disagreement above which an imagined step is not trusted, or
            ``None`` for the full horizon. Defaults to ``None``.
        num_candidates: candidate trajectories ``m``. Defaults to ``15``.
        horizon: imagined steps ``h``. Defaults to ``10``.
        value_module: module writing ``value_key`` (e.g. the PPO critic), evaluated at each
            candidate's last trusted state. Defaults to none.
        value_key: output key of ``value_module``. Defaults to ``"state_value"``.
        discount: discount of the score. Defaults to ``1.0``.
        action_key: action key. Defaults to ``"action"``.
        log_prob_key: log-prob key. Defaults to ``"action_log_prob"``.
        stats_key: key of the plan statistics, or ``None``. Defaults to ``"planner"``.

    Examples:
        >>> from torchrl_mbmf.envs import EnsembleLearnedDynamicsEnv, make_gym_state_env
        >>> from torchrl_mbmf.modules import (EnsembleDeltaDynamicsModel,
        ...                                   EnsemblePolicyGuidedPlanner, make_ppo_actor_critic)
        >>> real = make_gym_state_env("Pendulum-v1", seed=0)
        >>> actor, _ = make_ppo_actor_critic(real, hidden_sizes=(16, 16))
        >>> model = EnsembleDeltaDynamicsModel(3, 1, num_members=5, hidden_sizes=(16,))
        >>> planner = EnsemblePolicyGuidedPlanner(
        ...     EnsembleLearnedDynamicsEnv(model, real), actor, disagreement_threshold=0.05)
        >>> td = real.rollout(3, planner)
        >>> horizon = td["planner", "effective_horizon"]  # trusted steps of the chosen candidate
        >>> horizon.shape, td["planner", "disagreement"].shape
        (torch.Size([3, 1]), torch.Size([3, 1]))
        >>> bool(((horizon >= 0) & (horizon <= 10)).all())
        True
    """

    def __init__(
        self,
        env: ModelBasedEnvBase,
        actor: TensorDictModuleBase,
        *,
        disagreement_threshold: float | None = None,
        num_candidates: int = 15,
        horizon: int = 10,
        value_module: TensorDictModuleBase | None = None,
        value_key: NestedKey = "state_value",
        discount: float = 1.0,
        action_key: NestedKey = "action",
        log_prob_key: NestedKey = "action_log_prob",
        stats_key: NestedKey | None = "planner",
    ) -> None:
        from torchrl_mbmf.envs.model_based import LearnedDynamicsEnv

        if not isinstance(env, LearnedDynamicsEnv) or not isinstance(
            env.dynamics, EnsembleDeltaDynamicsModel
        ):
            model = getattr(env, "dynamics", None)
            raise TypeError(
                "env must be a LearnedDynamicsEnv on an EnsembleDeltaDynamicsModel, got "
                f"{type(env).__name__} on {type(model).__name__}"
            )
        if disagreement_threshold is not None:
            if isinstance(disagreement_threshold, bool) or not isinstance(
                disagreement_threshold, numbers.Real
            ):
                raise TypeError(
                    f"disagreement_threshold must be a float or None, got "
                    f"{disagreement_threshold!r}"
                )
            if not disagreement_threshold > 0:  # also rejects nan
                raise ValueError(
                    f"disagreement_threshold must be > 0 (or None for the full horizon), got "
                    f"{disagreement_threshold}"
                )
        super().__init__(
            env,
            actor,
            num_candidates=num_candidates,
            horizon=horizon,
            value_module=value_module,
            value_key=value_key,
            discount=discount,
            action_key=action_key,
            log_prob_key=log_prob_key,
            stats_key=stats_key,
        )
        self.disagreement_threshold = (
            None if disagreement_threshold is None else float(disagreement_threshold)
        )
        self.ensemble: EnsembleDeltaDynamicsModel = env.dynamics
        self.policy_rollout = None  # the fused rollout is for one model, not an ensemble
        self._last_plan: EnsemblePlan | None = None
        extra = getattr(env, "disagreement_key", None)
        if extra is not None:  # an output of the learned env, not an input of the planner
            self.in_keys = [k for k in self.in_keys if k != extra]
        if stats_key is not None:
            self.out_keys = [
                *self.out_keys,
                (stats_key, "effective_horizon"),
                (stats_key, "disagreement"),
            ]

    @property
    def tracks_disagreement(self) -> bool:
        """Whether the rollout evaluates every member (threshold or statistics need it)."""
        return self.disagreement_threshold is not None or self.stats_key is not None

    # ------------------------------------------------------------------ stages
    def _rollout_members(
        self, state: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None, torch.Tensor]:
        """Rolls ``[*B, m]`` candidates, candidate ``i`` in member ``i mod K``.

        Returns the first actions ``[*B, m, A]``, rewards ``[*B, m, h]``, trusted steps
        ``[*B, m]``, disagreement ``[*B, m, h]`` (or ``None``) and each candidate's last
        trusted state ``[*B, m, S]``.
        """
        fused = self._model_step()
        d, h, thr = self.ensemble.state_dim, self.horizon, self.disagreement_threshold
        s = expand_candidates(state, self.num_candidates)
        rewards = s.new_empty(*s.shape[:-1], h)
        track = self.tracks_disagreement
        disagreement = s.new_empty(*s.shape[:-1], h) if track else None
        trusted = torch.zeros(s.shape[:-1], dtype=torch.long, device=s.device)
        alive = torch.ones(s.shape[:-1], dtype=torch.bool, device=s.device)
        last, first, own_member = s, None, None
        for t in range(h):
            a = self.sample_candidate_actions(self.observation_of(s), t)
            if first is None:
                first = a
            if track:
                out = fused.members(s, a)  # [K, *B, m, S + 1]: every member on every candidate
                disagreement[..., t] = fused.disagreement(out)
                if own_member is None:
                    own_member = self._own_member_index(out.shape, out.device)
                out = out.gather(0, own_member).squeeze(0)
            else:
                out = fused.cyclic(s, a)  # each candidate through its own member only
            s = s + out[..., :d]
            rewards[..., t] = out[..., d]
            if thr is not None:
                alive = alive & (disagreement[..., t] <= thr)
                trusted += alive
                last = torch.where(alive.unsqueeze(-1), s, last)
        if thr is None:
            trusted.fill_(h)
            last = s
        return first, rewards, trusted, disagreement, last

    @staticmethod
    def _own_member_index(shape: torch.Size, device: torch.device) -> torch.Tensor:
        """Gather index ``[1, *B, m, S + 1]`` picking member ``i mod K`` for candidate ``i``."""
        k, m = shape[0], shape[-2]
        member = torch.arange(m, device=device) % k
        member = member.view(1, *([1] * (len(shape) - 3)), m, 1)
        return member.expand(1, *shape[1:])

    def score_truncated(
        self, rewards: torch.Tensor, trusted_steps: torch.Tensor, final: TensorDictBase
    ) -> torch.Tensor:
        """Candidate scores ``[*B, m]`` over each candidate's trusted steps only.

        ``sum_{t < T} discount^t r_t + discount^T V(s_T)`` with ``T = trusted_steps``; equal to
        the base class' :meth:`score_candidates` when every ``T`` is the horizon.

        Args:
            rewards: imagined rewards ``[*B, m, h]``.
            trusted_steps: ``T`` of every candidate ``[*B, m]``.
            final: the learned env's observation entries at each candidate's last trusted
                state, batch ``[*B, m]``.
        """
        h = rewards.shape[-1]
        steps = torch.arange(h, device=rewards.device)
        kept = rewards.masked_fill(steps >= trusted_steps.unsqueeze(-1), 0.0)
        total = discounted_return(kept, self.discount)
        if self.value_module is not None:
            value = self.terminal_value(final)
            if self.discount != 1.0:
                value = value * torch.pow(self.discount, trusted_steps.to(value.dtype))
            total = total + value
        return total

    def plan(self, tensordict: TensorDictBase) -> EnsemblePlan:
        """Rolls out in the members, scores the trusted steps and selects the best candidates.

        Args:
            tensordict: real states, batch ``[*B]``.

        Returns:
            The :class:`EnsemblePlan`.
        """
        with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
            state = tensordict.get(self.state_key)
            first, rewards, trusted, disagreement, last = self._rollout_members(state)
            returns = self.score_truncated(rewards, trusted, self._final_entries(last))
            plan = EnsemblePlan(first, returns, select_best(returns), trusted, disagreement)
        self._last_plan = plan
        return plan

    def forward(
        self,
        tensordict: TensorDictBase,
        tensordict_out: TensorDictBase | None = None,
        **kwargs: object,
    ) -> TensorDictBase:
        """Plans, writes the action (log-prob, ``loc``, ``scale``) and the plan statistics.

        Args:
            tensordict: the real env's tensordict, batch ``[*B]``; its entries are not changed.
            tensordict_out: where to write. Defaults to ``tensordict``.
        """
        self._last_plan = None
        out = super().forward(tensordict, tensordict_out, **kwargs)
        plan, self._last_plan = self._last_plan, None
        if self.stats_key is not None:
            returns = plan.returns
            horizon = plan.effective_horizon.to(returns.dtype).unsqueeze(-1)
            out.set((self.stats_key, "effective_horizon"), horizon)
            out.set(
                (self.stats_key, "disagreement"),
                plan.disagreement.mean((-2, -1)).unsqueeze(-1).to(returns.dtype),
            )
        return out


__all__ = ["EnsemblePlan", "EnsemblePolicyGuidedPlanner"]
