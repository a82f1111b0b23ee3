"""The shooting planner: expand, roll out with a candidate source, score, select, gather."""

from __future__ import annotations

import abc

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.data import Bounded
from torchrl.envs.model_based import ModelBasedEnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules.planners import MPCPlannerBase

from torchrl_mbmf.modules.planners.fast_model import CachedModelStep
from torchrl_mbmf.modules.planners.policy_rollout import PolicyRollout
from torchrl_mbmf.modules.planners.rollout import (
    CandidateSource,
    ImaginedRollout,
    SequenceMixture,
    Termination,
    Transition,
    TrustedHorizon,
    imagine,
    learned_model,
    model_transition,
)
from torchrl_mbmf.modules.planners.sampling import ActorSampler
from torchrl_mbmf.modules.planners.stages import (
    Plan,
    counted_steps,
    discounted_return,
    select_best,
    terminated_return,
    truncated_return,
)


# --------------------------------------------------------------------- planner
class ShootingPlanner(MPCPlannerBase, metaclass=abc.ABCMeta):
    """Base of the shooting planners: ``m`` candidates, ``h`` imagined steps, best first action.

    :meth:`plan` reads as four stages: expand each real state of the batch ``[*B]`` into
    ``[*B, m]`` candidates, roll them ``h`` steps in the learned env drawing each step's
    actions from :meth:`sample_candidate_actions`, score them with :meth:`score_candidates`
    (discounted sum of predicted rewards, plus the discounted terminal value when a
    ``value_module`` is given) and select the best candidate of each batch element, whose first
    action is written. Subclasses define how candidate actions are drawn; scoring is a
    replaceable hook too. Candidate sampling runs under ``torch.no_grad()`` and
    ``ExplorationType.RANDOM`` whatever the caller's mode.

    **Terminations.** A candidate's score stops at its first imagined terminal state (the
    learned env's ``terminated``): the reward of that step counts, later rewards and the
    terminal value do not (:func:`~torchrl_mbmf.modules.planners.terminated_return`). On every
    path: the tensor loops apply the env's own rule, ``env.rollout`` reports it.

    With a :class:`~torchrl_mbmf.envs.LearnedDynamicsEnv` the rollout is a plain tensor loop
    over the model's cached fused step (:class:`CachedModelStep`: no tensordict per step, no
    spec checks, no autograd, pre-packed oneDNN weights on CPU); any
    other env (any other :class:`~torchrl.envs.model_based.ModelBasedEnvBase`, a subclass of the
    learned env with its own ``_step``, a :class:`~torchrl.envs.TransformedEnv` around it, see
    :func:`~torchrl_mbmf.modules.planners.learned_model`) goes through ``env.rollout``.
    Both draw the same random numbers in the same order, so they choose the same action
    (``planner.fast_path = False`` forces the generic path). The policy-guided planner runs
    that loop fused (:class:`~torchrl_mbmf.modules.planners.PolicyRollout`:
    one ``[state, action]`` buffer, the actor's layers as single ``addmm`` calls, about a
    dozen tensor operations per imagined step), with results equal bit for bit to the
    step-by-step loop, which ``planner.fused_rollout = False`` selects.

    When an ``actor`` is given, the planner also writes the actor's distribution parameters
    (``loc``, ``scale``) at the real observation and the log-probability of the chosen action
    under them (``log_prob_key``), so the collected transitions feed PPO's loss.

    Args:
        env: the learned env (``batch_locked=False``) with a bounded continuous action spec.

    Keyword Args:
        num_candidates: candidate trajectories ``m``. Defaults to ``15``.
        horizon: imagined steps ``h``. Defaults to ``10``.
        actor: stochastic actor whose log-prob of the chosen action is written. Defaults to
            ``None``.
        value_module: TensorDict module writing ``value_key`` from the learned env's
            observation entries; its value at the last imagined state is added to the score.
            Defaults to ``None`` (thesis).
        value_key: output key of ``value_module``. Defaults to ``"state_value"``.
        discount: discount of the score. Defaults to ``1.0`` (the thesis' plain sum).
        action_key: action key. Defaults to ``"action"``.
        log_prob_key: key of the chosen action's log-prob. Defaults to ``None``: the actor's
            own ``log_prob_key`` (what TorchRL's losses built on that actor read), else
            ``"action_log_prob"``.
        stats_key: key under which ``best_return`` and ``mean_return`` of the candidates are
            written, or ``None``. Defaults to ``"planner"``.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.envs import LearnedDynamicsEnv, make_gym_state_env
        >>> from torchrl_mbmf.modules import DeltaDynamicsModel
        >>> from torchrl_mbmf.modules.planners import ShootingPlanner
        >>> class ZeroPlanner(ShootingPlanner):  # candidate sampling is the replaceable piece
        ...     def sample_candidate_actions(self, observation, step):
        ...         return observation.new_zeros(*observation.shape[:-1], self.action_dim)
        >>> real = make_gym_state_env("Pendulum-v1", seed=0)
        >>> env = LearnedDynamicsEnv(DeltaDynamicsModel(3, 1, hidden_sizes=(8,)), real)
        >>> ZeroPlanner(env, num_candidates=4, horizon=2)(real.reset())["action"]
        tensor([0.])
    """

    def __init__(
        self,
        env: ModelBasedEnvBase,
        *,
        num_candidates: int = 15,
        horizon: int = 10,
        actor: TensorDictModuleBase | None = None,
        value_module: TensorDictModuleBase | None = None,
        value_key: NestedKey = "state_value",
        discount: float = 1.0,
        action_key: NestedKey = "action",
        log_prob_key: NestedKey | None = None,
        stats_key: NestedKey | None = "planner",
    ) -> None:
        for name, value in (("num_candidates", num_candidates), ("horizon", horizon)):
            if isinstance(value, bool) or not isinstance(value, int):
                raise TypeError(f"{name} must be an integer >= 1, got {value!r}")
            if value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        if isinstance(discount, bool) or not isinstance(discount, int | float):
            raise TypeError(f"discount must be a number in (0, 1], got {discount!r}")
        if not 0.0 < discount <= 1.0:
            raise ValueError(f"discount must be in (0, 1], got {discount}")
        super().__init__(env, action_key=action_key)
        self.num_candidates = num_candidates
        self.horizon = horizon
        self.discount = float(discount)
        self.value_module = value_module
        self.value_key = value_key
        self.stats_key = stats_key
        spec = env.full_action_spec_unbatched[action_key]
        if not isinstance(spec, Bounded) or spec.domain != "continuous":
            raise ValueError(
                f"the env's {action_key!r} spec must be bounded and continuous (a torchrl "
                f"Bounded spec), got {type(spec).__name__}"
            )
        low, high = spec.space.low, spec.space.high
        self.action_dim = int(spec.shape[-1])
        self.register_buffer("action_low", low.clone(), persistent=False)
        self.register_buffer("action_high", high.clone(), persistent=False)
        self.fast_path = learned_model(env) is not None
        self._model_step = CachedModelStep(env.dynamics) if self.fast_path else None
        self.state_key: NestedKey = env.state_key if self.fast_path else self.in_keys[0]
        self.actor = actor
        self.sampler: ActorSampler | None = None
        if actor is not None:
            self.sampler = ActorSampler(actor)
            self._check_actor_size()
        if log_prob_key is None:
            log_prob_key = "action_log_prob" if self.sampler is None else self.sampler.log_prob_key
        self.log_prob_key = log_prob_key
        self.fused_rollout = True
        self.policy_rollout: PolicyRollout | None = None
        out_keys = [action_key]
        if self.sampler is not None:
            out_keys += [*self.sampler.param_keys, log_prob_key]
        if stats_key is not None:
            out_keys += [(stats_key, "best_return"), (stats_key, "mean_return")]
        self.out_keys = out_keys

    def _check_actor_size(self) -> None:
        obs_key = self.sampler.observation_key
        spec = self.env.full_observation_spec_unbatched
        if obs_key not in spec.keys(True):
            raise KeyError(
                f"the actor reads {obs_key!r}, which the learned env does not produce; it "
                f"produces {sorted(map(str, spec.keys(True, True)))}"
            )
        obs = spec[obs_key].zero()
        try:
            with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
                action = self.sampler.sample(obs.unsqueeze(0))
        except RuntimeError as err:
            raise ValueError(
                f"the actor cannot read the env's {obs_key!r} of shape {tuple(obs.shape)}: {err}"
            ) from err
        if action.shape[-1] != self.action_dim:
            raise ValueError(
                f"the actor's actions have size {action.shape[-1]}, the env's action spec "
                f"has size {self.action_dim}"
            )

    # ------------------------------------------------------------------- hooks
    @abc.abstractmethod
    def sample_candidate_actions(self, observation: torch.Tensor, step: int) -> torch.Tensor:
        """Candidate actions ``[*B, m, action_dim]`` for imagined ``step`` (0-based).

        Args:
            observation: the candidates' current policy observations ``[*B, m, obs_dim]``
                (the state when the learned env has no separate observation).
            step: the imagined step.
        """

    def score_candidates(
        self,
        rewards: torch.Tensor,
        final: TensorDictBase | None,
        trusted_steps: torch.Tensor | None = None,
        terminated: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Candidate scores ``[*B, m]``: discounted return plus the optional terminal value.

        A candidate that reaches a terminal state scores the rewards up to and including
        that step, nothing after it and no terminal value
        (:func:`~torchrl_mbmf.modules.planners.terminated_return`). An overriding hook is
        called with the rewards after each candidate's terminal step zeroed (and, with an
        adaptive horizon, the steps counted up to that terminal step as ``trusted_steps``).

        Args:
            rewards: imagined rewards ``[*B, m, h]``.
            final: the learned env's observation entries at the last (trusted) imagined
                state, batch ``[*B, m]`` (``None`` when no score reads it).
            trusted_steps: each candidate's trusted steps ``[*B, m]`` (adaptive horizon:
                :func:`~torchrl_mbmf.modules.planners.truncated_return`), or ``None`` for
                the whole horizon. Defaults to ``None``.
            terminated: whether each imagined step reached a terminal state ``[*B, m, h]``,
                or ``None`` when the env never terminates. Defaults to ``None``.
        """
        value = self.terminal_value(final) if self.value_module is not None else None
        if terminated is not None:
            return terminated_return(rewards, terminated, self.discount, value, trusted_steps)
        if trusted_steps is None:
            return discounted_return(rewards, self.discount, value)
        return truncated_return(rewards, trusted_steps, self.discount, value)

    def terminal_value(self, final: TensorDictBase) -> torch.Tensor:
        """``value_module``'s value ``[*B, m]`` at the last imagined state."""
        return self.value_module(final.copy()).get(self.value_key)[..., 0]

    def termination(self) -> Termination | None:
        """The learned env's terminal-state rule for this plan, or ``None`` if it never ends."""
        if getattr(self.env, "never_terminates", False):
            return None
        return self.env.terminated

    def transition(self) -> Transition:
        """The world model's step for this plan (its cached folded weights)."""
        return model_transition(self._model_step())

    def horizon_mask(self) -> TrustedHorizon | None:
        """The adaptive-horizon mask of a plan, or ``None`` for the whole horizon."""
        return None

    def refined_sequences(self, rollout: ImaginedRollout, returns: torch.Tensor) -> torch.Tensor:
        """Open-loop sequences ``[*B, n, h, A]`` for the next round (refining planners).

        Called ``refinement_rounds`` times, with the previous round's rollout and scores.
        """
        raise NotImplementedError(f"{type(self).__name__} has no refinement rounds")

    refinement_rounds = 0
    plan_class: type[Plan] = Plan

    # ---------------------------------------------------------------- rollouts
    def observation_of(self, state: torch.Tensor) -> torch.Tensor:
        """What the actor reads at an imagined state (fast path)."""
        obs = self.env.observation(state)
        return state if obs is None else obs

    def candidate_source(self) -> CandidateSource:
        """The candidates' actions: :meth:`sample_candidate_actions` at their observations."""

        def source(state: torch.Tensor, step: int) -> torch.Tensor:
            return self.sample_candidate_actions(self.observation_of(state), step)

        return source

    def _final_entries(self, state: torch.Tensor) -> TensorDictBase:
        entries = {self.state_key: state}
        if self.env.observation_key is not None:
            entries[self.env.observation_key] = self.env.observation(state)
        return TensorDict(entries, batch_size=state.shape[:-1])

    def rollout(
        self, state: torch.Tensor, source: CandidateSource | None = None
    ) -> ImaginedRollout:
        """Rolls the candidates of the real states ``[*B, S]`` out in the learned model.

        Args:
            state: real states.
            source: the candidate source. Defaults to :meth:`candidate_source`; the
                policy-guided planner then runs its fused loop when it can.
        """
        rollout = self.policy_rollout
        if (
            source is None
            and self.fused_rollout
            and rollout is not None
            and rollout.model_step is self._model_step
        ):
            out = rollout(
                state,
                num_candidates=self.num_candidates,
                horizon=self.horizon,
                termination=self.termination(),
            )
            if out is not None:
                first, rewards, final, terminated = out
                return ImaginedRollout(first, rewards, final, terminated=terminated)
        return imagine(
            state,
            num_candidates=self.num_candidates,
            horizon=self.horizon,
            source=self.candidate_source() if source is None else source,
            transition=self.transition(),
            trust=self.horizon_mask(),
            keep_actions=self.refinement_rounds > 0,
            termination=self.termination(),
        )

    def _rollout_generic(
        self, tensordict: TensorDictBase
    ) -> tuple[torch.Tensor, torch.Tensor, TensorDictBase, torch.Tensor]:
        env = self.env
        start = tensordict.select(*self.in_keys).unsqueeze(-1)
        start = start.expand(*tensordict.batch_size, self.num_candidates).clone()
        if self.sampler is not None:
            obs_key = self.sampler.observation_key
        else:
            obs_key = getattr(env, "observation_key", None) or self.state_key
        planner = self

        class _CandidateSampler:
            step = 0

            def __call__(self, td: TensorDictBase) -> TensorDictBase:
                actions = planner.sample_candidate_actions(td.get(obs_key), self.step)
                td.set(planner.action_key, actions)
                self.step += 1
                return td

        rollout = env.rollout(
            self.horizon,
            policy=_CandidateSampler(),
            tensordict=env.reset(start),
            auto_reset=False,
            break_when_any_done=False,
        )
        first = rollout.get(self.action_key)[..., 0, :]
        rewards = rollout.get(("next", "reward"))[..., 0]
        final = rollout.get("next")[..., -1].select(*self.in_keys)
        nxt = rollout.get("next")
        key = "terminated" if "terminated" in nxt else "done"
        terminated = nxt.get(key, None)
        if terminated is None:
            terminated = torch.zeros(rewards.shape, dtype=torch.bool, device=rewards.device)
        else:
            terminated = terminated.reshape(rewards.shape).bool()
        return first, rewards, final, terminated

    def _scored(
        self, state: torch.Tensor, source: CandidateSource | None
    ) -> tuple[ImaginedRollout, torch.Tensor]:
        out = self.rollout(state, source)
        final = self._final_entries(out.final_state) if self._reads_final() else None
        return out, self._score(out.rewards, final, out.trusted_steps, out.terminated)

    def _score(
        self,
        rewards: torch.Tensor,
        final: TensorDictBase | None,
        trusted_steps: torch.Tensor | None,
        terminated: torch.Tensor | None,
    ) -> torch.Tensor:
        if terminated is not None:
            if type(self).score_candidates is ShootingPlanner.score_candidates:
                return self.score_candidates(rewards, final, trusted_steps, terminated)
            # an overridden hook sees the rewards after each candidate's terminal step zeroed
            # (and, when it is given trusted steps, the counted steps as those)
            counted, _ = counted_steps(terminated, trusted_steps)
            steps = torch.arange(rewards.shape[-1], device=rewards.device)
            rewards = rewards.masked_fill(steps >= counted.unsqueeze(-1), 0.0)
            if trusted_steps is not None:
                trusted_steps = counted
        if trusted_steps is None:  # the two-argument hook of planners that override it
            return self.score_candidates(rewards, final)
        return self.score_candidates(rewards, final, trusted_steps)

    def plan(self, tensordict: TensorDictBase) -> Plan:
        """Expands, rolls out, scores and selects the candidates of every batch element.

        With ``refinement_rounds`` the rounds after the first roll out the mixture of the
        candidate source and :meth:`refined_sequences`; the plan is then over the candidates
        of every round.

        Args:
            tensordict: real states, batch ``[*B]``.

        Returns:
            The :class:`Plan`, with the statistics the planner writes.
        """
        state = tensordict.get(self.state_key, None)
        if state is None:
            raise KeyError(
                f"{type(self).__name__} plans from {self.state_key!r}, which its input lacks "
                f"(keys: {sorted(map(str, tensordict.keys(True, True)))})"
            )
        if not torch.isfinite(state).all():
            raise ValueError(
                f"{type(self).__name__} got a NaN or Inf {self.state_key!r}: no plan can start "
                "from it"
            )
        with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
            if not self.fast_path:
                first, rewards, final, terminated = self._rollout_generic(tensordict)
                returns = self._score(rewards, final, None, terminated)
                return Plan(first, returns, select_best(returns))
            out, returns = self._scored(state, None)
            if not self.refinement_rounds:
                best = select_best(returns)
                return self.plan_class(
                    out.first_actions, returns, best, out.trusted_steps, out.disagreement
                )
            firsts, scores = [out.first_actions], [returns]
            for _ in range(self.refinement_rounds):
                source = SequenceMixture(
                    self.candidate_source(), self.refined_sequences(out, returns)
                )
                out, returns = self._scored(state, source)
                firsts.append(out.first_actions)
                scores.append(returns)
            returns = torch.cat(scores, dim=-1)
            return Plan(torch.cat(firsts, dim=-2), returns, select_best(returns))

    def _reads_final(self) -> bool:
        # the stock score reads the last imagined state only for a terminal value
        stock = type(self).score_candidates is ShootingPlanner.score_candidates
        return self.value_module is not None or not stock

    def planning(self, td: TensorDictBase) -> torch.Tensor:
        """The action to execute now ``[*B, action_dim]`` (``MPCPlannerBase`` contract)."""
        return self.plan(td).action

    def forward(
        self,
        tensordict: TensorDictBase,
        tensordict_out: TensorDictBase | None = None,
        **kwargs: object,
    ) -> TensorDictBase:
        """Plans from each real state and writes the chosen action (and log-prob, stats).

        Args:
            tensordict: the real env's tensordict, batch ``[*B]``; its entries are not changed.
            tensordict_out: where to write. Defaults to ``tensordict``.
        """
        if kwargs:
            raise TypeError(f"unexpected arguments {sorted(kwargs)}")
        plan = self.plan(tensordict)
        # the spec's projection for a bounded box, without its per-call membership check
        action = torch.maximum(torch.minimum(plan.action, self.action_high), self.action_low)
        out = tensordict if tensordict_out is None else tensordict_out
        out.set(self.action_key, action)
        if self.sampler is not None:
            with torch.no_grad():
                obs = tensordict.get(self.sampler.observation_key)
                lp = self.sampler.log_prob(obs, action)
            for key in self.sampler.param_keys:
                out.set(key, lp[key])
            out.set(self.log_prob_key, lp["log_prob"])
        if self.stats_key is not None:
            for name, value in plan.statistics().items():
                out.set((self.stats_key, name), value)
        return out


__all__ = ["ShootingPlanner"]
