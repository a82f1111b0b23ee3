"""Policy-guided MPC on an ensemble world model, with an uncertainty-adaptive horizon."""

from __future__ import annotations

import numbers
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.model_based import ModelBasedEnvBase

from torchrl_mbmf.modules.ensemble import EnsembleDeltaDynamicsModel
from torchrl_mbmf.modules.planners.policy_guided import PolicyGuidedMPCPlanner
from torchrl_mbmf.modules.planners.rollout import MemberTransition, TrustedHorizon, learned_model
from torchrl_mbmf.modules.planners.stages import Plan


class EnsemblePlan(Plan):
    """The plan of :class:`EnsemblePolicyGuidedPlanner`: a :class:`Plan` with its trust record.

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
    :func:`~torchrl_mbmf.world_model.ensemble_fit.calibrate_disagreement_threshold`.

    **Speed.** Each imagined step runs all ``K`` members on all candidates in one batched op
    per layer (``K`` times one model's FLOPs), which the disagreement needs, and keeps each
    candidate's own member's prediction. When neither a threshold nor ``stats_key`` is set, the
    disagreement is not needed and each candidate goes through its own member only (candidates
    grouped ``[*B, m] -> [*B, m/K, K]``, one model's FLOPs); both paths give the same plan.

    **Refinement** (``refinement="cem"`` or ``"mppi"``, LOOP's acting with ``"mppi"`` and a
    min-Q ``value_module``): the rounds of
    :class:`~torchrl_mbmf.modules.PolicyGuidedMPCPlanner`'s refinement, with the ensemble's
    score in every round. Candidate ``i`` of every round (the first
    ``round(policy_fraction * m)`` closed-loop policy samples, then the open-loop sequences
    drawn from the refitted Gaussian) rolls in member ``i mod K`` and is scored by that
    member's return, the score that picks the action without refinement (not the members'
    mean return, nor a pessimistic minimum over members): CEM's elites and MPPI's weights
    ``softmax((R - max R) / (temperature * std R))`` are taken over these single-member
    scores, and the executed action is the first action of the best candidate over all
    rounds. The adaptive horizon and terminations cut the score in every round.

    Besides ``best_return`` and ``mean_return``, ``stats_key`` receives
    ``effective_horizon`` (the chosen candidate's trusted steps, ``[*B, 1]``) and
    ``disagreement`` (the mean disagreement over all candidates, of every round, and imagined
    steps of the plan, ``[*B, 1]``).

    Args:
        env: a :class:`~torchrl_mbmf.envs.LearnedDynamicsEnv` (or
            :class:`~torchrl_mbmf.envs.EnsembleLearnedDynamicsEnv`) on an ensemble.
        actor: the stochastic actor (a ``ProbabilisticActor``), reading the policy observation.

    Keyword Args:
        disagreement_threshold: disagreement above which an imagined step is not trusted, or
            ``None`` for the full horizon. Defaults to ``None``.
        **kwargs: the keyword arguments of
            :class:`~torchrl_mbmf.modules.PolicyGuidedMPCPlanner`, with its defaults (a
            ``value_module`` is evaluated at each candidate's last trusted state):
            ``num_candidates`` (``m = 15``), ``horizon`` (``h = 10``), ``value_module``
            (none: the thesis), ``value_key``, ``discount`` (``1.0``), ``action_key``,
            ``log_prob_key``, ``stats_key`` (``"planner"``), and the refinement's
            ``refinement`` (``None``), ``iterations`` (``2``), ``num_elites`` (``3``),
            ``policy_fraction`` (``1/3``), ``temperature`` (``1.0``) and ``min_std``
            (``0.05``).

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
        **kwargs: Any,
    ) -> None:
        model = learned_model(env)
        if model is None or model.ensemble_size < 2:
            model = getattr(env, "dynamics", None)
            raise TypeError(
                "env must be a LearnedDynamicsEnv on an EnsembleDeltaDynamicsModel (an ensemble, "
                "ensemble_size >= 2), stepped as its model (not wrapped in a TransformedEnv, no "
                f"_step of its own), got {type(env).__name__} on {type(model).__name__}"
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
        super().__init__(env, actor, **kwargs)
        self.disagreement_threshold = (
            None if disagreement_threshold is None else float(disagreement_threshold)
        )
        self.ensemble: EnsembleDeltaDynamicsModel = env.dynamics
        self.policy_rollout = None  # the fused rollout is for one model, not an ensemble
        extra = getattr(env, "disagreement_key", None)
        if extra is not None:  # an output of the learned env, not an input of the planner
            self.in_keys = [k for k in self.in_keys if k != extra]
        if self.stats_key is not None:
            self.out_keys = [
                *self.out_keys,
                (self.stats_key, "effective_horizon"),
                (self.stats_key, "disagreement"),
            ]

    plan_class = EnsemblePlan

    @property
    def tracks_disagreement(self) -> bool:
        """Whether the rollout evaluates every member (threshold or statistics need it)."""
        return self.disagreement_threshold is not None or self.stats_key is not None

    # ------------------------------------------------------------------ stages
    def transition(self) -> MemberTransition:
        """Each candidate in its own member, with the disagreement when it is needed."""
        return MemberTransition(self._model_step(), self.tracks_disagreement)

    def horizon_mask(self) -> TrustedHorizon:
        """The adaptive horizon of ``disagreement_threshold`` (``None``: the whole horizon)."""
        return TrustedHorizon(self.disagreement_threshold)

    def score_truncated(
        self, rewards: torch.Tensor, trusted_steps: torch.Tensor, final: TensorDictBase | None
    ) -> torch.Tensor:
        """Candidate scores ``[*B, m]`` over each candidate's trusted steps only.

        ``sum_{t < T} discount^t r_t + discount^T V(s_T)`` with ``T = trusted_steps``:
        :meth:`score_candidates` with ``trusted_steps``.

        Args:
            rewards: imagined rewards ``[*B, m, h]``.
            trusted_steps: ``T`` of every candidate ``[*B, m]``.
            final: the learned env's observation entries at each candidate's last trusted
                state, batch ``[*B, m]``.
        """
        return self.score_candidates(rewards, final, trusted_steps)


__all__ = ["EnsemblePlan", "EnsemblePolicyGuidedPlanner"]
