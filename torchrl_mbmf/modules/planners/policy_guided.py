"""Policy-guided MPC: candidate actions sampled from the PPO/SAC policy (thesis section 5.3)."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.envs.model_based import ModelBasedEnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_mbmf.modules.planners.common import Plan, ShootingPlanner, expand_candidates
from torchrl_mbmf.modules.planners.fast_model import CachedModelStep
from torchrl_mbmf.modules.planners.policy_rollout import PolicyRollout

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
    ``loc``/``scale`` and the action's log-probability (``action_log_prob``): batches collected
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
        num_candidates: candidate trajectories ``m``. Defaults to ``15``.
        horizon: imagined steps ``h``. Defaults to ``10``.
        value_module: module writing ``value_key`` (e.g. the PPO critic); its value at the last
            imagined state is added to the score. Defaults to none (thesis).
        value_key: output key of ``value_module``. Defaults to ``"state_value"``.
        discount: discount of the score. Defaults to ``1.0``.
        action_key: action key. Defaults to ``"action"``.
        log_prob_key: log-prob key. Defaults to ``"action_log_prob"``.
        stats_key: key of the candidates' best/mean predicted return. Defaults to ``"planner"``.
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
        refinement: str | None = None,
        iterations: int = 2,
        num_elites: int = 3,
        policy_fraction: float = 1 / 3,
        temperature: float = 1.0,
        min_std: float = 0.05,
    ) -> None:
        if actor is None:
            raise TypeError("PolicyGuidedMPCPlanner needs a stochastic actor, got None")
        if refinement not in REFINEMENTS:
            raise ValueError(f"refinement must be one of {REFINEMENTS}, got {refinement!r}")
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
        self.refinement = refinement
        if refinement is not None:
            if not self.fast_path:
                raise ValueError(
                    f"refinement={refinement!r} needs a LearnedDynamicsEnv, got "
                    f"{type(env).__name__}"
                )
            if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 1:
                raise ValueError(f"iterations must be an integer >= 1, got {iterations!r}")
            if not 1 <= num_elites <= num_candidates:
                raise ValueError(
                    f"num_elites must be in [1, num_candidates={num_candidates}], got {num_elites}"
                )
            if not 0.0 <= policy_fraction < 1.0:
                raise ValueError(f"policy_fraction must be in [0, 1), got {policy_fraction}")
            if temperature <= 0:
                raise ValueError(f"temperature must be > 0, got {temperature}")
            if min_std < 0:
                raise ValueError(f"min_std must be >= 0, got {min_std}")
        self.iterations = int(iterations)
        self.num_elites = int(num_elites)
        self.num_policy = round(policy_fraction * num_candidates)
        self.temperature = float(temperature)
        self.min_std = float(min_std)
        if self.fast_path and refinement is None and self._samples_the_actor():
            observation = self.env.observation
            self.policy_rollout = PolicyRollout(self._model_step, self.sampler, observation)

    def _samples_the_actor(self) -> bool:
        """Whether candidates are the stock policy samples (subclasses may draw otherwise)."""
        cls = type(self)
        return (
            cls.sample_candidate_actions is PolicyGuidedMPCPlanner.sample_candidate_actions
            and cls.observation_of is ShootingPlanner.observation_of
            and cls._rollout_fast is ShootingPlanner._rollout_fast
            and type(self._model_step) is CachedModelStep
        )

    def sample_candidate_actions(self, observation: torch.Tensor, step: int) -> torch.Tensor:
        """Actions sampled from the actor at each candidate's observation."""
        return self.sampler.sample(observation)

    # ------------------------------------------------------------------ refinement
    def _rollout_sequences(
        self, state: torch.Tensor, sequences: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor, TensorDictBase]:
        """Rolls ``m`` candidates; the last ``n`` follow ``sequences`` ``[*B, n, h, A]``.

        The first ``m - n`` candidates (all of them without ``sequences``) sample the policy
        at each imagined state. Returns every candidate's actions ``[*B, m, h, A]``, rewards
        ``[*B, m, h]`` and final entries.
        """
        predict = self._model_step()
        s = expand_candidates(state, self.num_candidates)
        n_pol = self.num_candidates - (0 if sequences is None else sequences.shape[-3])
        actions = s.new_empty(*s.shape[:-1], self.horizon, self.action_dim)
        rewards = s.new_empty(*s.shape[:-1], self.horizon)
        for t in range(self.horizon):
            if sequences is None:
                a = self.sample_candidate_actions(self.observation_of(s), t)
            elif n_pol:
                a_pol = self.sample_candidate_actions(self.observation_of(s[..., :n_pol, :]), t)
                a = torch.cat([a_pol, sequences[..., t, :]], dim=-2)
            else:
                a = sequences[..., t, :]
            actions[..., t, :] = a
            s, r = predict(s, a)
            rewards[..., t] = r[..., 0]
        return actions, rewards, self._final_entries(s)

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

    def plan(self, tensordict: TensorDictBase) -> Plan:
        """Plans as the base class; with ``refinement`` adds the CEM/MPPI rounds.

        Args:
            tensordict: real states, batch ``[*B]``.

        Returns:
            The :class:`~torchrl_mbmf.modules.planners.Plan` over the candidates of every
            round (``first_actions`` ``[*B, m * (iterations + 1), A]``).
        """
        if self.refinement is None:
            return super().plan(tensordict)
        with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
            state = tensordict.get(self.state_key)
            actions, rewards, final = self._rollout_sequences(state, None)
            returns = self.score_candidates(rewards, final)
            firsts, scores = [actions[..., 0, :]], [returns]
            n_seq = self.num_candidates - self.num_policy
            for _ in range(self.iterations):
                mean, std = self._refit(actions, returns)
                noise = torch.randn(
                    *mean.shape[:-2], n_seq, *mean.shape[-2:], dtype=mean.dtype, device=mean.device
                )
                seqs = mean.unsqueeze(-3) + std.unsqueeze(-3) * noise
                seqs = torch.maximum(torch.minimum(seqs, self.action_high), self.action_low)
                actions, rewards, final = self._rollout_sequences(state, seqs)
                returns = self.score_candidates(rewards, final)
                firsts.append(actions[..., 0, :])
                scores.append(returns)
            first = torch.cat(firsts, dim=-2)
            returns = torch.cat(scores, dim=-1)
            return Plan(first, returns, returns.argmax(-1))
