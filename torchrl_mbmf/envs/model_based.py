"""The learned world model as a TorchRL environment."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Literal

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Bounded, Categorical, Composite, TensorSpec, Unbounded
from torchrl.envs import EnvBase, TransformedEnv
from torchrl.envs.model_based import ModelBasedEnvBase

from torchrl_mbmf.envs.factory import flat_transforms
from torchrl_mbmf.envs.keys import OBSERVATION_KEY, STATE_KEY
from torchrl_mbmf.envs.terminations import (
    NeverTerminates,
    TerminationFn,
    TerminationRule,
    termination_rule_of_env,
)
from torchrl_mbmf.envs.transforms.observation import StateToObservation
from torchrl_mbmf.modules.dynamics import DeltaDynamicsModel

#: How an ensemble steps a batch: ``"cycle"``, element ``i`` of the last batch dim in member
#: ``i mod K``; ``"mean"``, the members' mean.
MEMBER_ASSIGNMENTS = ("cycle", "mean")


def _find_state_to_observation(
    env: EnvBase, state_key: NestedKey, observation_key: NestedKey
) -> StateToObservation | None:
    while isinstance(env, TransformedEnv):
        for t in flat_transforms(env.transform):
            if (
                isinstance(t, StateToObservation)
                and t.in_keys[0] == state_key
                and t.out_keys[0] == observation_key
            ):
                return t
        env = env.base_env
    return None


def _unbounded_like(spec: TensorSpec) -> Unbounded:
    return Unbounded(shape=spec.shape, dtype=spec.dtype, device=spec.device)


def _check_termination_fn(
    fn: TerminationFn, state_dim: int, device: torch.device, dtype: torch.dtype
) -> None:
    """Calls ``fn`` on two zero states: it must return a bool tensor ``[2]``."""
    if not callable(fn):
        raise TypeError(f"termination_fn must be a callable on states or None, got {fn!r}")
    if isinstance(fn, TerminationRule) and state_dim < fn.min_state_dim:
        raise ValueError(
            f"termination_fn {fn!r} reads states of at least {fn.min_state_dim} entries, the "
            f"world model's state has {state_dim}"
        )
    with torch.no_grad():
        out = fn(torch.zeros(2, state_dim, device=device, dtype=dtype))
    if not isinstance(out, torch.Tensor) or out.dtype != torch.bool or out.shape != (2,):
        got = (
            f"{out.dtype} tensor of shape {tuple(out.shape)}"
            if isinstance(out, torch.Tensor)
            else type(out).__name__
        )
        raise ValueError(
            "termination_fn must map states [..., state_dim] to a bool tensor [...]; on states "
            f"of shape (2, {state_dim}) it returned a {got}"
        )


def _adopt_action_bounds(
    model: DeltaDynamicsModel, spec: TensorSpec, action_key: NestedKey
) -> None:
    """Sets the model's action clip to the env's action spec, or refuses other bounds."""
    if not isinstance(spec, Bounded):
        return
    low, high = spec.space.low.flatten(), spec.space.high.flatten()
    uniform = bool((low == low[0]).all() and (high == high[0]).all())
    env_bounds = f"[{low.tolist()}, {high.tolist()}]" if not uniform else None
    if uniform:
        env_bounds = f"[{float(low[0])}, {float(high[0])}]"
    own = model.action_bounds
    if own is None:
        if uniform:  # per-dimension bounds: the model keeps no clip of its own
            model.set_action_bounds(float(low[0]), float(high[0]))
        return
    same = uniform and all(
        math.isclose(a, float(b), rel_tol=1e-6, abs_tol=1e-7)
        for a, b in zip(own, (low[0], high[0]), strict=True)
    )
    if not same:
        raise ValueError(
            f"the world model clips actions to [{own[0]}, {own[1]}] but the real env's "
            f"{action_key!r} spec is {env_bounds}: build the model with the env's bounds "
            "(action_low/action_high), or with none (the learned env then adopts the spec)"
        )


def _check_arguments(
    world_model: DeltaDynamicsModel,
    env: EnvBase,
    member_assignment: str | None,
    disagreement_key: NestedKey | None,
) -> None:
    """The types of the model and the env, and the ensemble-only arguments."""
    if not isinstance(world_model, DeltaDynamicsModel):
        raise TypeError(
            f"world_model must be a DeltaDynamicsModel, got {type(world_model).__name__}"
        )
    if not isinstance(env, EnvBase):
        raise TypeError(
            f"env must be the real TorchRL env (an EnvBase) whose specs and start states the "
            f"learned env takes, got {type(env).__name__}"
        )
    if member_assignment is not None and member_assignment not in MEMBER_ASSIGNMENTS:
        raise ValueError(
            f"member_assignment must be one of {MEMBER_ASSIGNMENTS}, got {member_assignment!r}"
        )
    members = member_assignment is not None or disagreement_key is not None
    if members and world_model.ensemble_size < 2:
        raise TypeError(
            "member_assignment and disagreement_key need an ensemble (ensemble_size >= 2, "
            f"such as an EnsembleDeltaDynamicsModel), got {type(world_model).__name__} with "
            f"ensemble_size={world_model.ensemble_size}"
        )


def _check_model_fits_env(
    world_model: DeltaDynamicsModel, env: EnvBase, state_key: NestedKey, action_key: NestedKey
) -> tuple[Composite, TensorSpec]:
    """The real env's unbatched observation spec and action spec, checked against the model."""
    obs_spec = env.full_observation_spec_unbatched
    if state_key not in obs_spec.keys(True):
        raise KeyError(
            f"the real env has no {state_key!r} entry in its observation spec; "
            f"its entries are {sorted(map(str, obs_spec.keys(True, True)))}"
        )
    state_spec = obs_spec[state_key]
    model_dtype = next(world_model.parameters()).dtype
    if state_spec.dtype != model_dtype:
        raise TypeError(
            f"the real env's {state_key!r} is {state_spec.dtype}, the world model computes in "
            f"{model_dtype}: add torchrl.envs.DoubleToFloat() to the real env (or build the "
            "model in its dtype)"
        )
    if state_spec.shape[-1:] != (world_model.state_dim,):
        raise ValueError(
            f"the real env's {state_key!r} has shape {tuple(state_spec.shape)}, the world "
            f"model expects state_dim={world_model.state_dim}"
        )
    action_spec = env.full_action_spec_unbatched[action_key]
    if action_spec.shape[-1:] != (world_model.action_dim,):
        raise ValueError(
            f"the real env's {action_key!r} has shape {tuple(action_spec.shape)}, the world "
            f"model expects action_dim={world_model.action_dim}"
        )
    return obs_spec, action_spec


def _learned_specs(
    obs_spec: Composite,
    action_spec: TensorSpec,
    keys: tuple[NestedKey, NestedKey | None, NestedKey, NestedKey, NestedKey | None],
    batch_size: torch.Size,
    device: torch.device,
) -> tuple[Composite, Composite, Composite, Composite]:
    """The learned env's observation, action, reward and done specs.

    ``keys`` are the state, observation (or ``None``), action, reward and disagreement (or
    ``None``) keys. A learned model may predict outside the real env's observation bounds:
    the observation specs are unbounded.
    """
    state_key, observation_key, action_key, reward_key, disagreement_key = keys
    bs = batch_size
    entries = {state_key: _unbounded_like(obs_spec[state_key])}
    if observation_key is not None:
        entries[observation_key] = _unbounded_like(obs_spec[observation_key])
    observation = Composite(entries).expand(bs).to(device)
    if disagreement_key is not None:
        observation[disagreement_key] = Unbounded(shape=(*bs, 1), device=device)
    action = Composite(
        {action_key: action_spec.clone().expand(*bs, *action_spec.shape)}, shape=bs
    ).to(device)
    reward = Composite({reward_key: Unbounded(shape=(*bs, 1), device=device)}, shape=bs)
    done = Composite(
        done=Categorical(2, shape=(*bs, 1), dtype=torch.bool, device=device),
        terminated=Categorical(2, shape=(*bs, 1), dtype=torch.bool, device=device),
        shape=bs,
    )
    return observation, action, reward, done


class _RealStarts:
    """Start states drawn from the real env's ``reset`` (shared, not copied, with the env)."""

    def __init__(self, env: EnvBase | None, state_key: NestedKey) -> None:
        self.env = env
        self.state_key = state_key

    def __deepcopy__(self, memo: dict) -> _RealStarts:
        return self

    def __getstate__(self) -> dict[str, object]:
        return {"env": None, "state_key": self.state_key}

    def __call__(self, n: int) -> torch.Tensor:
        if self.env is None:
            raise RuntimeError(
                "this learned env has no real env to draw start states from (it was pickled); "
                f"pass them: env.reset(TensorDict({{{self.state_key!r}: states}}, batch_size))"
            )
        states, count = [], 0
        while count < n:
            state = self.env.reset().get(self.state_key)
            state = state.reshape(-1, state.shape[-1])
            states.append(state)
            count += state.shape[0]
        return torch.cat(states)[:n]


class LearnedDynamicsEnv(ModelBasedEnvBase):
    """A :class:`~torchrl_mbmf.modules.DeltaDynamicsModel` as a stateless TorchRL environment.

    ``reset`` takes the state from the tensordict it is given (``state_key``; without one, the
    real env's initial states); each ``step`` writes the model's next state, its policy
    observation, the predicted reward and ``terminated`` from ``termination_fn``. It never
    auto-resets and accepts any batch shape, so ``[*B, m]`` candidates roll out in one call.
    The model adopts the env's action bounds. :meth:`predict` steps plain tensors. Specs,
    terminations, start states and ensembles: ``docs/design/learned_env.md``.

    Args:
        world_model: the fitted dynamics model.
        env: the real env whose specs are copied (batched or not).

    Keyword Args:
        batch_size: batch size of the specs. Defaults to ``torch.Size([])``.
        state_key: key of the model state. Defaults to :data:`~torchrl_mbmf.envs.STATE_KEY`.
        observation_key: key of the policy observation, or ``None`` if the policy reads the
            state itself. Defaults to :data:`~torchrl_mbmf.envs.OBSERVATION_KEY` (``None`` is
            used when the real env has no such entry or when it is the state key).
        action_key: action key. Defaults to ``"action"``.
        reward_key: reward key. Defaults to ``"reward"``.
        observation_fn: maps a state tensor to the policy observation. Defaults to the real
            env's ``StateToObservation`` transform.
        device: device of the env. Defaults to the world model's device.
        member_assignment: ``"cycle"`` (element ``i`` of the last batch dim in member
            ``i mod K``) or ``"mean"`` (ensembles only). Defaults to ``None``: the members'
            mean.
        disagreement_key: key of the members' disagreement ``[*B, 1]`` written at every step
            (ensembles only), or ``None``. Defaults to ``None``.
        termination_fn: ``fn(next_states [..., state_dim]) -> bool [...]``, the terminal
            states. Defaults to ``None``: the known rule of the real env's task.

    Examples:
        >>> import torch
        >>> from torchrl.envs.utils import check_env_specs
        >>> from torchrl_mbmf.envs import LearnedDynamicsEnv, make_gym_state_env
        >>> from torchrl_mbmf.modules import DeltaDynamicsModel
        >>> real = make_gym_state_env("Pendulum-v1")
        >>> model_env = LearnedDynamicsEnv(DeltaDynamicsModel(3, 1, hidden_sizes=(16,)), real)
        >>> check_env_specs(model_env)
        >>> start = real.reset().expand(15)  # 15 candidates from one real state
        >>> rollout = model_env.rollout(10, tensordict=model_env.reset(start), auto_reset=False)
        >>> rollout["next", "reward"].shape
        torch.Size([15, 10, 1])
    """

    def __init__(
        self,
        world_model: DeltaDynamicsModel,
        env: EnvBase,
        *,
        batch_size: torch.Size | tuple[int, ...] | None = None,
        state_key: NestedKey = STATE_KEY,
        observation_key: NestedKey | None = OBSERVATION_KEY,
        action_key: NestedKey = "action",
        reward_key: NestedKey = "reward",
        observation_fn: Callable[[torch.Tensor], torch.Tensor] | None = None,
        device: torch.device | str | None = None,
        member_assignment: Literal["cycle", "mean"] | None = None,
        disagreement_key: NestedKey | None = None,
        termination_fn: TerminationFn | None = None,
    ) -> None:
        _check_arguments(world_model, env, member_assignment, disagreement_key)
        if device is None:
            device = next(world_model.parameters()).device
        module = world_model.as_tensordict_module(
            state_key=state_key, action_key=action_key, reward_key=reward_key
        )
        super().__init__(module, device=device, batch_size=batch_size)
        self.dynamics = world_model
        self.state_key = state_key
        obs_spec, action_spec = _check_model_fits_env(world_model, env, state_key, action_key)
        _adopt_action_bounds(world_model, action_spec, action_key)
        if termination_fn is None:
            termination_fn = termination_rule_of_env(env)
        model_dtype = next(world_model.parameters()).dtype
        _check_termination_fn(
            termination_fn, world_model.state_dim, torch.device(self.device), model_dtype
        )
        self.termination_fn = termination_fn
        self._starts = _RealStarts(env, state_key)
        if observation_key is not None and (
            observation_key not in obs_spec.keys(True) or observation_key == state_key
        ):
            observation_key = None  # the policy reads the state itself
        self.observation_key = observation_key
        self._observation_fn: Callable[[torch.Tensor], torch.Tensor] | None = None
        if observation_key is not None:
            if observation_fn is None:
                transform = _find_state_to_observation(env, state_key, observation_key)
                if transform is None:
                    raise ValueError(
                        f"the real env has an {observation_key!r} entry but no "
                        f"StateToObservation transform from {state_key!r}; pass observation_fn"
                    )
                observation_fn = transform.observation
            self._observation_fn = observation_fn
        keys = (state_key, observation_key, action_key, reward_key)
        if disagreement_key is not None and disagreement_key in keys:
            raise ValueError(f"disagreement_key={disagreement_key!r} collides with another key")
        self.member_assignment = member_assignment
        self.disagreement_key = disagreement_key
        observation, action, reward, done = _learned_specs(
            obs_spec,
            action_spec,
            (state_key, observation_key, action_key, reward_key, disagreement_key),
            self.batch_size,
            torch.device(self.device),
        )
        self.observation_spec = observation
        self.full_action_spec = action
        self.full_reward_spec = reward
        self.full_done_spec = done

    def observation(self, state: torch.Tensor) -> torch.Tensor | None:
        """The policy observation of ``state`` (``None`` when there is no observation key)."""
        if self._observation_fn is None:
            return None
        return self._observation_fn(state)

    def _members_of(self, batch_size: torch.Size) -> torch.Tensor | None:
        if self.member_assignment != "cycle":
            return None
        return self.dynamics.cyclic_member_index(batch_size, self.dynamics.num_members)

    def predict(
        self, state: torch.Tensor, action: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Tensor-level step: next state ``[..., state_dim]`` and reward ``[..., 1]``.

        Args:
            state: states ``[*B, state_dim]``.
            action: actions ``[*B, action_dim]``.
        """
        if self.member_assignment == "cycle":
            return self.dynamics(state, action, self._members_of(state.shape[:-1]))
        return self.dynamics(state, action)

    def fast_predictor(self) -> Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, ...]]:
        """Inference-only :meth:`predict` with the model's scaling folded into its weights.

        A snapshot of the current weights (see
        :meth:`~torchrl_mbmf.modules.DeltaDynamicsModel.fused_step`); planners build one per
        plan. With ``member_assignment="cycle"`` only each element's own member is evaluated.
        """
        if self.member_assignment != "cycle":
            return self.dynamics.fused_step()
        fused, d = self.dynamics.fused_members(), self.dynamics.state_dim

        def step(state: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, ...]:
            out = fused.cyclic(state, action)
            return state + out[..., :d], out[..., d:]

        return step

    def steps_as_its_model(self) -> bool:
        """Whether a step is exactly :meth:`predict` then :meth:`terminated` (planners' fast path).

        ``False`` for a subclass that overrides ``_step``, :meth:`predict` or the way it fills
        the step's entries: the planners then roll out through ``env.rollout``.
        """
        cls = type(self)
        base = LearnedDynamicsEnv
        return all(
            getattr(cls, name) is getattr(base, name) for name in ("_step", "predict", "_fill")
        )

    @property
    def never_terminates(self) -> bool:
        """Whether ``termination_fn`` is the rule of a task without terminal states."""
        return isinstance(self.termination_fn, NeverTerminates)

    def terminated(self, state: torch.Tensor) -> torch.Tensor:
        """``termination_fn`` of the states ``[*B, state_dim]``: bool ``[*B]``."""
        return self.termination_fn(state)

    def _fill(
        self, state: torch.Tensor, batch_size: torch.Size, terminated: torch.Tensor | None = None
    ) -> TensorDict:
        out = TensorDict({self.state_key: state}, batch_size=batch_size, device=self.device)
        if self.observation_key is not None:
            out.set(self.observation_key, self.observation(state))
        if terminated is None:
            terminated = torch.zeros((*batch_size, 1), dtype=torch.bool, device=self.device)
        out.set("done", terminated.clone())
        out.set("terminated", terminated)
        return out

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        state, action = tensordict.get(self.state_key), tensordict.get(self.action_key)
        if self.disagreement_key is None:
            next_state, reward = self.predict(state, action)
        else:
            members = self._members_of(tensordict.batch_size)
            next_state, reward, disagreement = self.dynamics.predict_with_disagreement(
                state, action, members
            )
        terminated = self.terminated(next_state).unsqueeze(-1)
        out = self._fill(next_state, tensordict.batch_size, terminated)
        out.set(self.reward_key, reward)
        if self.disagreement_key is not None:
            out.set(self.disagreement_key, disagreement.unsqueeze(-1))
        return out

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: object) -> TensorDictBase:
        if tensordict is not None and self.state_key in tensordict.keys(True):
            state = tensordict.get(self.state_key)
            batch_size = tensordict.batch_size
        else:
            # No start state given (e.g. check_env_specs): the real env's initial states.
            batch_size = tensordict.batch_size if tensordict is not None else self.batch_size
            state = self._starts(batch_size.numel()).to(self.device)
            state = state.reshape(*batch_size, state.shape[-1])
        if state.shape[-1] != self.dynamics.state_dim:
            raise ValueError(
                f"reset state {self.state_key!r} has last dim {state.shape[-1]}, expected "
                f"{self.dynamics.state_dim}"
            )
        out = self._fill(state, batch_size)
        if self.disagreement_key is not None:  # no prediction made yet
            out.set(self.disagreement_key, state.new_zeros(*batch_size, 1))
        return out

    def _set_seed(self, seed: int | None) -> None:
        # The learned env is deterministic: nothing to seed.
        return None
