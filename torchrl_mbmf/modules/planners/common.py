"""Shared stages of the shooting planners: roll out, score, select."""

from __future__ import annotations

import abc
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.envs.model_based import ModelBasedEnvBase
from torchrl.modules.planners import MPCPlannerBase

from torchrl_mbmf.modules.planners.sampling import ActorSampler


@dataclass
class Plan:
    """The outcome of one planning call.

    Attributes:
        first_actions: first action of every candidate ``[*B, m, action_dim]``.
        returns: score of every candidate ``[*B, m]``.
        best: index of the chosen candidate ``[*B]``.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.modules.planners import Plan
        >>> plan = Plan(torch.zeros(2, 3, 1), torch.tensor([[0., 2., 1.], [3., 0., 0.]]),
        ...             torch.tensor([1, 0]))
        >>> plan.action.shape
        torch.Size([2, 1])
    """

    first_actions: torch.Tensor
    returns: torch.Tensor
    best: torch.Tensor

    @property
    def action(self) -> torch.Tensor:
        """First action of the best candidate ``[*B, action_dim]``."""
        index = self.best[..., None, None].expand(*self.best.shape, 1, self.first_actions.shape[-1])
        return self.first_actions.gather(-2, index).squeeze(-2)


def select_best(returns: torch.Tensor) -> torch.Tensor:
    """Index of the highest-scoring candidate along the last dim (first one on ties).

    Args:
        returns: candidate scores ``[*B, m]``.

    Returns:
        ``[*B]`` indices.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.modules.planners import select_best
        >>> select_best(torch.tensor([[1.0, 3.0, 3.0]]))
        tensor([1])
    """
    return returns.argmax(-1)


class ShootingPlanner(MPCPlannerBase, metaclass=abc.ABCMeta):
    """Base of the shooting planners: ``m`` candidates, ``h`` imagined steps, best first action.

    For a real-state batch ``[*B]`` the planner expands to ``[*B, m]`` candidates, rolls them
    ``h`` steps in the learned env drawing each step's actions from
    :meth:`sample_actions`, scores them with :meth:`score` (discounted sum of predicted
    rewards, plus the discounted terminal value when a ``value_module`` is given) and writes
    the first action of the best candidate of each batch element. Subclasses define only how
    candidate actions are drawn.

    With a :class:`~torchrl_mbmf.envs.LearnedDynamicsEnv` the rollout is a plain tensor loop
    over :meth:`~torchrl_mbmf.envs.LearnedDynamicsEnv.predict` (no tensordict per step, no spec
    checks, no autograd); any other
    :class:`~torchrl.envs.model_based.ModelBasedEnvBase` goes through ``env.rollout``. Both
    draw the same random numbers in the same order, so they choose the same action
    (``planner.fast_path = False`` forces the generic path).

    When an ``actor`` is given, the planner also writes the actor's distribution parameters
    (``loc``, ``scale``) at the real observation and the log-probability of the chosen action
    under them (``log_prob_key``), so the collected transitions feed PPO's loss.

    Args:
        env: the learned env (``batch_locked=False``).

    Keyword Args:
        num_candidates: candidate trajectories ``m``. Defaults to ``15``.
        horizon: imagined steps ``h``. Defaults to ``10``.
        actor: stochastic actor whose log-prob of the chosen action is written. Defaults to none.
        value_module: TensorDict module writing ``value_key`` from the observation; its value
            at the last imagined state is added to the score. Defaults to none (thesis).
        value_key: output key of ``value_module``. Defaults to ``"state_value"``.
        discount: discount of the score. Defaults to ``1.0`` (the thesis' plain sum).
        action_key: action key. Defaults to ``"action"``.
        log_prob_key: key of the chosen action's log-prob. Defaults to ``"action_log_prob"``.
        stats_key: key under which ``best_return`` and ``mean_return`` of the candidates are
            written, or ``None``. Defaults to ``"planner"``.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.envs import LearnedDynamicsEnv, make_gym_state_env
        >>> from torchrl_mbmf.modules import DeltaDynamicsModel
        >>> from torchrl_mbmf.modules.planners import ShootingPlanner
        >>> class ZeroPlanner(ShootingPlanner):  # candidate sampling is the replaceable piece
        ...     def sample_actions(self, observation, step):
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
        log_prob_key: NestedKey = "action_log_prob",
        stats_key: NestedKey | None = "planner",
    ) -> None:
        if not isinstance(num_candidates, int) or num_candidates < 1:
            raise ValueError(f"num_candidates must be an integer >= 1, got {num_candidates!r}")
        if not isinstance(horizon, int) or horizon < 1:
            raise ValueError(f"horizon must be an integer >= 1, got {horizon!r}")
        if not 0.0 < discount <= 1.0:
            raise ValueError(f"discount must be in (0, 1], got {discount}")
        super().__init__(env, action_key=action_key)
        self.num_candidates = num_candidates
        self.horizon = horizon
        self.discount = float(discount)
        self.value_module = value_module
        self.value_key = value_key
        self.log_prob_key = log_prob_key
        self.stats_key = stats_key
        spec = env.full_action_spec_unbatched[action_key]
        self.action_dim = int(spec.shape[-1])
        self.register_buffer("action_low", spec.space.low.clone(), persistent=False)
        self.register_buffer("action_high", spec.space.high.clone(), persistent=False)
        from torchrl_mbmf.envs.model_based import LearnedDynamicsEnv

        self.fast_path = isinstance(env, LearnedDynamicsEnv)
        self.state_key: NestedKey = env.state_key if self.fast_path else self.in_keys[0]
        self.actor = actor
        self.sampler: ActorSampler | None = None
        if actor is not None:
            self.sampler = ActorSampler(actor)
            self._check_actor_size()
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
            with torch.no_grad():
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

    # ----------------------------------------------------------------- stages
    @abc.abstractmethod
    def sample_actions(self, observation: torch.Tensor, step: int) -> torch.Tensor:
        """Candidate actions ``[*B, m, action_dim]`` for imagined ``step`` (0-based).

        Args:
            observation: the candidates' current observations ``[*B, m, obs_dim]``.
            step: the imagined step.
        """

    def observation_of(self, state: torch.Tensor) -> torch.Tensor:
        """What the actor and value module read at an imagined state."""
        if self.fast_path:
            obs = self.env.observation(state)
            return state if obs is None else obs
        return state

    def terminal_value(self, observation: torch.Tensor) -> torch.Tensor:
        """Value ``[*B, m]`` of the last imagined observation (0 without a value module)."""
        if self.value_module is None:
            return observation.new_zeros(observation.shape[:-1])
        key = self.value_module.in_keys[0]
        td = TensorDict({key: observation}, batch_size=observation.shape[:-1])
        return self.value_module(td).get(self.value_key)[..., 0]

    def score(self, rewards: torch.Tensor, final_observation: torch.Tensor) -> torch.Tensor:
        """Candidate scores ``[*B, m]`` from imagined rewards ``[*B, m, h]``.

        ``sum_t discount**t * r_t + discount**h * V(s_h)``.
        """
        h = rewards.shape[-1]
        weights = self.discount ** torch.arange(h, dtype=rewards.dtype, device=rewards.device)
        total = (rewards * weights).sum(-1)
        if self.value_module is not None:
            total = total + self.discount**h * self.terminal_value(final_observation)
        return total

    # --------------------------------------------------------------- rollouts
    def _rollout_fast(self, state: torch.Tensor) -> tuple[torch.Tensor, ...]:
        predict = self.env.fast_predictor()
        s = state.unsqueeze(-2).expand(*state.shape[:-1], self.num_candidates, state.shape[-1])
        rewards = []
        first = None
        for t in range(self.horizon):
            a = self.sample_actions(self.observation_of(s), t)
            if first is None:
                first = a
            s, r = predict(s, a)
            rewards.append(r[..., 0])
        return first, torch.stack(rewards, -1), self.observation_of(s)

    def _rollout_generic(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, ...]:
        env = self.env
        batch = (*tensordict.batch_size, self.num_candidates)
        start = tensordict.select(*self.in_keys).unsqueeze(-1).expand(batch).clone()
        obs_key = self.sampler.observation_key if self.sampler is not None else self.state_key
        planner = self

        class _Sampler:
            t = 0

            def __call__(self, td: TensorDictBase) -> TensorDictBase:
                td.set(planner.action_key, planner.sample_actions(td.get(obs_key), self.t))
                self.t += 1
                return td

        rollout = env.rollout(
            self.horizon,
            policy=_Sampler(),
            tensordict=env.reset(start),
            auto_reset=False,
            break_when_any_done=False,
        )
        first = rollout.get(self.action_key)[..., 0, :]
        rewards = rollout.get(("next", "reward"))[..., 0]
        final = rollout.get(("next", obs_key))[..., -1, :]
        return first, rewards, final

    def plan(self, tensordict: TensorDictBase) -> Plan:
        """Rolls out and scores the candidates of every batch element of ``tensordict``.

        Args:
            tensordict: real states, batch ``[*B]``.

        Returns:
            The :class:`Plan`.
        """
        with torch.no_grad():
            if self.fast_path:
                first, rewards, final = self._rollout_fast(tensordict.get(self.state_key))
            else:
                first, rewards, final = self._rollout_generic(tensordict)
            returns = self.score(rewards, final)
            return Plan(first, returns, select_best(returns))

    def planning(self, td: TensorDictBase) -> torch.Tensor:
        """The action to execute now ``[*B, action_dim]`` (``MPCPlannerBase`` contract)."""
        return self.plan(td).action

    def forward(
        self,
        tensordict: TensorDictBase,
        tensordict_out: TensorDictBase | None = None,
        **kwargs: object,
    ) -> TensorDictBase:
        """Plans from each real state and writes the chosen action (and log-prob, stats)."""
        if kwargs:
            raise TypeError(f"unexpected arguments {sorted(kwargs)}")
        plan = self.plan(tensordict)
        action = self.action_spec.project(plan.action) if self.action_spec.shape else plan.action
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
            out.set((self.stats_key, "best_return"), plan.returns.max(-1).values.unsqueeze(-1))
            out.set((self.stats_key, "mean_return"), plan.returns.mean(-1).unsqueeze(-1))
        return out
