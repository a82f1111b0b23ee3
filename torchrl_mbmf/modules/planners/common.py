"""The shooting planner: expand, roll out with a candidate source, score, select, gather."""

from __future__ import annotations

import abc

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.data import Bounded
from torchrl.envs.model_based import ModelBasedEnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules.planners import MPCPlannerBase

from torchrl_mbmf.modules.planners.env_rollout import check_actor_fits, rollout_in_env
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
from torchrl_mbmf.modules.planners.scoring import CandidateScoring
from torchrl_mbmf.modules.planners.stages import Plan, select_best


# --------------------------------------------------------------------- planner
class ShootingPlanner(CandidateScoring, MPCPlannerBase, metaclass=abc.ABCMeta):
    """Base of the shooting planners: ``m`` candidates, ``h`` imagined steps, best first action.

    :meth:`plan` expands each real state ``[*B]`` into ``[*B, m]`` candidates, rolls them
    ``h`` steps with actions from :meth:`sample_candidate_actions` (``no_grad``, random
    exploration), scores them (:meth:`score_candidates`) and writes the best candidate's
    first action; with an ``actor``, also the actor's ``loc``/``scale`` and the action's
    log-prob (for PPO's loss). A :class:`~torchrl_mbmf.envs.LearnedDynamicsEnv` takes a tensor
    loop (fused for policy samples, :class:`PolicyRollout`), any other env ``env.rollout``,
    with the same random draws and choice (``fast_path`` / ``fused_rollout = False`` force
    the slower paths). Design notes: ``docs/design/planners.md``.

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
            own ``log_prob_key``, else ``"action_log_prob"``.
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
        _check_sizes(num_candidates, horizon, discount)
        super().__init__(env, action_key=action_key)
        self.num_candidates = num_candidates
        self.horizon = horizon
        self.discount = float(discount)
        self.value_module = value_module
        self.value_key = value_key
        self.stats_key = stats_key
        low, high = _action_bounds(env, action_key)
        self.action_dim = int(low.shape[-1])
        self.register_buffer("action_low", low.clone(), persistent=False)
        self.register_buffer("action_high", high.clone(), persistent=False)
        self.fast_path = learned_model(env) is not None
        self._model_step = CachedModelStep(env.dynamics) if self.fast_path else None
        self.state_key: NestedKey = env.state_key if self.fast_path else self.in_keys[0]
        self.actor = actor
        self.sampler: ActorSampler | None = None
        if actor is not None:
            self.sampler = ActorSampler(actor)
            check_actor_fits(self.sampler, env, self.action_dim)
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

    # ------------------------------------------------------------------- hooks
    @abc.abstractmethod
    def sample_candidate_actions(self, observation: torch.Tensor, step: int) -> torch.Tensor:
        """Candidate actions ``[*B, m, action_dim]`` for imagined ``step`` (0-based).

        Args:
            observation: the candidates' current policy observations ``[*B, m, obs_dim]``
                (the state when the learned env has no separate observation).
            step: the imagined step.
        """

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
        """Open-loop sequences ``[*B, n, h, A]`` for the next round, from the last one's."""
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

    def rollout(
        self, state: torch.Tensor, source: CandidateSource | None = None
    ) -> ImaginedRollout:
        """Rolls the candidates of the real states ``[*B, S]`` out in the learned model.

        Args:
            state: real states.
            source: the candidate source. Defaults to :meth:`candidate_source` (or the fused
                policy loop when it applies).
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

    def _scored(
        self, state: torch.Tensor, source: CandidateSource | None
    ) -> tuple[ImaginedRollout, torch.Tensor]:
        out = self.rollout(state, source)
        final = self._final_entries(out.final_state) if self._reads_final() else None
        return out, self._score(out.rewards, final, out.trusted_steps, out.terminated)

    def plan(self, tensordict: TensorDictBase) -> Plan:
        """Expands, rolls out, scores and selects the candidates of every batch element.

        With ``refinement_rounds``, later rounds roll out the mixture of the candidate
        source and :meth:`refined_sequences`; the plan is over every round's candidates (and
        their trusted steps and disagreement, when the rollouts record them).

        Args:
            tensordict: real states, batch ``[*B]``.

        Returns:
            The :class:`Plan`, with the statistics the planner writes.
        """
        state = _start_state(type(self).__name__, self.state_key, tensordict)
        with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
            if not self.fast_path:
                first, rewards, final, terminated = rollout_in_env(self, tensordict)
                returns = self._score(rewards, final, None, terminated)
                return Plan(first, returns, select_best(returns))
            out, returns = self._scored(state, None)
            if not self.refinement_rounds:
                best = select_best(returns)
                return self.plan_class(
                    out.first_actions, returns, best, out.trusted_steps, out.disagreement
                )
            return _refined_plan(self, state, out, returns)

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


def _refined_plan(
    planner: ShootingPlanner, state: torch.Tensor, out: ImaginedRollout, returns: torch.Tensor
) -> Plan:
    """The plan over the first round ``(out, returns)`` and ``refinement_rounds`` more."""
    rounds = [(out, returns)]
    for _ in range(planner.refinement_rounds):
        source = SequenceMixture(
            planner.candidate_source(), planner.refined_sequences(out, returns)
        )
        out, returns = planner._scored(state, source)
        rounds.append((out, returns))
    returns = torch.cat([r for _, r in rounds], dim=-1)
    return planner.plan_class(
        torch.cat([o.first_actions for o, _ in rounds], dim=-2),
        returns,
        select_best(returns),
        _joined([o.trusted_steps for o, _ in rounds], dim=-1),
        _joined([o.disagreement for o, _ in rounds], dim=-2),
    )


def _joined(parts: list[torch.Tensor | None], dim: int) -> torch.Tensor | None:
    """The rounds' per-candidate records side by side, or ``None`` when the rounds have none."""
    return None if parts[0] is None else torch.cat(parts, dim=dim)


def _check_sizes(num_candidates: int, horizon: int, discount: float) -> None:
    for name, value in (("num_candidates", num_candidates), ("horizon", horizon)):
        if isinstance(value, bool) or not isinstance(value, int):
            raise TypeError(f"{name} must be an integer >= 1, got {value!r}")
        if value < 1:
            raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
    if isinstance(discount, bool) or not isinstance(discount, int | float):
        raise TypeError(f"discount must be a number in (0, 1], got {discount!r}")
    if not 0.0 < discount <= 1.0:
        raise ValueError(f"discount must be in (0, 1], got {discount}")


def _action_bounds(env: ModelBasedEnvBase, action_key: NestedKey) -> tuple[torch.Tensor, ...]:
    spec = env.full_action_spec_unbatched[action_key]
    if not isinstance(spec, Bounded) or spec.domain != "continuous":
        raise ValueError(
            f"the env's {action_key!r} spec must be bounded and continuous (a torchrl "
            f"Bounded spec), got {type(spec).__name__}"
        )
    return spec.space.low, spec.space.high


def _start_state(name: str, state_key: NestedKey, tensordict: TensorDictBase) -> torch.Tensor:
    state = tensordict.get(state_key, None)
    if state is None:
        raise KeyError(
            f"{name} plans from {state_key!r}, which its input lacks "
            f"(keys: {sorted(map(str, tensordict.keys(True, True)))})"
        )
    if not torch.isfinite(state).all():
        raise ValueError(f"{name} got a NaN or Inf {state_key!r}: no plan can start from it")
    return state


__all__ = ["ShootingPlanner"]
