"""Derives the policy observation from the full model state."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Composite, TensorSpec, Unbounded
from torchrl.envs.transforms import Transform

from torchrl_mbmf.envs.keys import OBSERVATION_KEY, STATE_KEY


class StateToObservation(Transform):
    """Writes the policy observation as the state with some dimensions dropped.

    The world model works on the full thesis state (x position first), but policies and critics
    must not see the absolute x position, which grows without bound. This transform keeps the two
    views in sync: ``observation = state[..., keep]`` where ``keep`` are all dims not listed in
    ``drop_dims``. The same object is used by :class:`~torchrl_mbmf.envs.LearnedDynamicsEnv`
    (through :meth:`observation`) so real and imagined observations are computed identically.

    Args:
        state_dim: size of the last dim of the state.

    Keyword Args:
        drop_dims: indices of the state dims hidden from the policy. Defaults to ``(0,)`` (the x
            position of HalfCheetah's thesis state).
        in_key: the state key. Defaults to :data:`~torchrl_mbmf.envs.STATE_KEY`.
        out_key: the observation key. Defaults to :data:`~torchrl_mbmf.envs.OBSERVATION_KEY`.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_mbmf.envs.transforms import StateToObservation
        >>> t = StateToObservation(4, drop_dims=(0,))
        >>> td = t(TensorDict(state=torch.arange(4.0)))
        >>> td["observation"]
        tensor([1., 2., 3.])
    """

    def __init__(
        self,
        state_dim: int,
        *,
        drop_dims: Sequence[int] = (0,),
        in_key: NestedKey = STATE_KEY,
        out_key: NestedKey = OBSERVATION_KEY,
    ) -> None:
        if state_dim < 1:
            raise ValueError(f"state_dim must be >= 1, got {state_dim}")
        dropped = {d % state_dim for d in drop_dims}
        if any(not -state_dim <= d < state_dim for d in drop_dims):
            raise ValueError(f"drop_dims={tuple(drop_dims)} out of range for state_dim={state_dim}")
        keep = [i for i in range(state_dim) if i not in dropped]
        if not keep:
            raise ValueError(f"drop_dims={tuple(drop_dims)} would drop every state dim")
        super().__init__(in_keys=[in_key], out_keys=[out_key])
        self.state_dim = state_dim
        self.drop_dims = tuple(sorted(dropped))
        self.register_buffer("keep_index", torch.tensor(keep, dtype=torch.long), persistent=False)
        self._contiguous = keep == list(range(keep[0], keep[-1] + 1))
        self._start, self._stop = keep[0], keep[-1] + 1

    @property
    def observation_dim(self) -> int:
        """Size of the policy observation."""
        return int(self.keep_index.numel())

    def observation(self, state: torch.Tensor) -> torch.Tensor:
        """Maps a state ``[..., state_dim]`` to the observation ``[..., observation_dim]``."""
        if state.shape[-1] != self.state_dim:
            raise ValueError(
                f"state has last dim {state.shape[-1]}, expected state_dim={self.state_dim}"
            )
        if self._contiguous:
            return state[..., self._start : self._stop]
        return state.index_select(-1, self.keep_index.to(state.device))

    def _apply_transform(self, state: torch.Tensor) -> torch.Tensor:
        return self.observation(state)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        next_tensordict.set(
            self.out_keys[0], self.observation(next_tensordict.get(self.in_keys[0]))
        )
        return next_tensordict

    def _reset(
        self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
    ) -> TensorDictBase:
        return self._call(tensordict_reset)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        """Adds the observation entry, shaped ``[*batch, observation_dim]``."""
        state_spec: TensorSpec = observation_spec[self.in_keys[0]]
        observation_spec[self.out_keys[0]] = Unbounded(
            shape=(*state_spec.shape[:-1], self.observation_dim),
            dtype=state_spec.dtype,
            device=state_spec.device,
        )
        return observation_spec
