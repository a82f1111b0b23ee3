"""The ensemble world model as a TorchRL environment that reports the members' disagreement."""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Unbounded
from torchrl.envs import EnvBase

from torchrl_mbmf.envs.keys import OBSERVATION_KEY, STATE_KEY
from torchrl_mbmf.envs.model_based import LearnedDynamicsEnv
from torchrl_mbmf.modules.ensemble import EnsembleDeltaDynamicsModel

MEMBER_ASSIGNMENTS = ("cycle", "mean")


class EnsembleLearnedDynamicsEnv(LearnedDynamicsEnv):
    """A :class:`~torchrl_mbmf.modules.EnsembleDeltaDynamicsModel` as a TorchRL environment.

    :class:`~torchrl_mbmf.envs.LearnedDynamicsEnv` accepts the ensemble unchanged, but steps the
    members' mean and does not expose their disagreement. This subclass rolls every batch
    element in one member and writes the disagreement of each step. With
    ``member_assignment="cycle"`` element ``i`` of the last batch dim is stepped by member
    ``i mod K`` (an unbatched env uses member 0), the convention of
    :class:`~torchrl_mbmf.modules.planners.EnsemblePolicyGuidedPlanner`: ``[*B, m]`` candidates
    rolled out here follow the same members as in the planner. ``"mean"`` steps the members'
    mean, as ``LearnedDynamicsEnv`` does.

    Every step writes ``("next", disagreement_key)`` ``[*B, 1]``: the disagreement of the
    members at the step's ``(state, action)``
    (:meth:`~torchrl_mbmf.modules.EnsembleDeltaDynamicsModel.disagreement`). It is an
    observation entry of the env's spec; ``reset`` writes 0 (no prediction made yet). All
    members are evaluated at every step (one batched op), which is needed for the disagreement.
    Everything else (keys, specs, stateless reset from the given state, no auto-reset, any batch
    shape) is as in ``LearnedDynamicsEnv``.

    Args:
        world_model: the fitted ensemble.
        env: the real env whose specs are copied (batched or not).

    Keyword Args:
        member_assignment: ``"cycle"`` or ``"mean"`` (see above). Defaults to ``"cycle"``.
        disagreement_key: key of the disagreement. Defaults to ``"disagreement"``.
        batch_size: batch size of the specs. Defaults to ``torch.Size([])``.
        state_key: key of the model state. Defaults to :data:`~torchrl_mbmf.envs.STATE_KEY`.
        observation_key: key of the policy observation, or ``None``. Defaults to
            :data:`~torchrl_mbmf.envs.OBSERVATION_KEY`.
        action_key: action key. Defaults to ``"action"``.
        reward_key: reward key. Defaults to ``"reward"``.
        observation_fn: maps a state tensor to the policy observation. Defaults to the real
            env's ``StateToObservation`` transform.
        device: device of the env. Defaults to the world model's device.

    Examples:
        >>> import torch
        >>> from torchrl.envs.utils import check_env_specs
        >>> from torchrl_mbmf.envs import EnsembleLearnedDynamicsEnv, make_gym_state_env
        >>> from torchrl_mbmf.modules import EnsembleDeltaDynamicsModel
        >>> real = make_gym_state_env("Pendulum-v1", seed=0)
        >>> model = EnsembleDeltaDynamicsModel(3, 1, num_members=3, hidden_sizes=(16,))
        >>> env = EnsembleLearnedDynamicsEnv(model, real)
        >>> check_env_specs(env)
        >>> start = real.reset().expand(6)  # 6 candidates: members 0, 1, 2, 0, 1, 2
        >>> rollout = env.rollout(4, tensordict=env.reset(start), auto_reset=False)
        >>> rollout["next", "disagreement"].shape
        torch.Size([6, 4, 1])
    """

    def __init__(
        self,
        world_model: EnsembleDeltaDynamicsModel,
        env: EnvBase,
        *,
        member_assignment: Literal["cycle", "mean"] = "cycle",
        disagreement_key: NestedKey = "disagreement",
        batch_size: torch.Size | tuple[int, ...] | None = None,
        state_key: NestedKey = STATE_KEY,
        observation_key: NestedKey | None = OBSERVATION_KEY,
        action_key: NestedKey = "action",
        reward_key: NestedKey = "reward",
        observation_fn: Callable[[torch.Tensor], torch.Tensor] | None = None,
        device: torch.device | str | None = None,
    ) -> None:
        if not isinstance(world_model, EnsembleDeltaDynamicsModel):
            raise TypeError(
                "world_model must be an EnsembleDeltaDynamicsModel, got "
                f"{type(world_model).__name__} (use LearnedDynamicsEnv for a single model)"
            )
        if member_assignment not in MEMBER_ASSIGNMENTS:
            raise ValueError(
                f"member_assignment must be one of {MEMBER_ASSIGNMENTS}, got {member_assignment!r}"
            )
        super().__init__(
            world_model,
            env,
            batch_size=batch_size,
            state_key=state_key,
            observation_key=observation_key,
            action_key=action_key,
            reward_key=reward_key,
            observation_fn=observation_fn,
            device=device,
        )
        if disagreement_key in (state_key, observation_key, action_key, reward_key):
            raise ValueError(f"disagreement_key={disagreement_key!r} collides with another key")
        self.member_assignment = member_assignment
        self.disagreement_key = disagreement_key
        spec = self.observation_spec.clone()
        spec[disagreement_key] = Unbounded(shape=(*self.batch_size, 1), device=self.device)
        self.observation_spec = spec

    def _members_of(self, batch_size: torch.Size) -> torch.Tensor | None:
        if self.member_assignment == "mean":
            return None
        return EnsembleDeltaDynamicsModel.cyclic_member_index(batch_size, self.dynamics.num_members)

    def predict(
        self, state: torch.Tensor, action: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Tensor-level step (each element in its member): next state and reward ``[..., 1]``.

        Args:
            state: states ``[*B, state_dim]``.
            action: actions ``[*B, action_dim]``.
        """
        return self.dynamics(state, action, self._members_of(state.shape[:-1]))

    def fast_predictor(self) -> Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, ...]]:
        """Inference-only :meth:`predict` with the scaling folded into the members' weights.

        With ``"cycle"`` only each element's own member is evaluated (no disagreement).
        """
        fused = self.dynamics.fused_members()
        if self.member_assignment == "mean":
            return fused
        d = self.dynamics.state_dim

        def step(state: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, ...]:
            out = fused.cyclic(state, action)
            return state + out[..., :d], out[..., d:]

        return step

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        state = tensordict.get(self.state_key)
        next_state, reward, disagreement = self.dynamics.predict_with_disagreement(
            state, tensordict.get(self.action_key), self._members_of(tensordict.batch_size)
        )
        out = self._fill(next_state, tensordict.batch_size)
        out.set(self.reward_key, reward)
        out.set(self.disagreement_key, disagreement.unsqueeze(-1))
        return out

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: object) -> TensorDictBase:
        out = super()._reset(tensordict, **kwargs)
        state = out.get(self.state_key)
        out.set(self.disagreement_key, state.new_zeros(*out.batch_size, 1))
        return out


__all__ = ["MEMBER_ASSIGNMENTS", "EnsembleLearnedDynamicsEnv"]
