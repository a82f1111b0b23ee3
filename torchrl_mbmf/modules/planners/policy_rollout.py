"""The policy-guided rollout of a plan as one tight tensor loop."""

from __future__ import annotations

from collections.abc import Callable

import torch

from torchrl_mbmf.modules.planners.fast_model import CachedModelStep
from torchrl_mbmf.modules.planners.rollout import Termination
from torchrl_mbmf.modules.planners.sampling import ActorSampler

ObservationFn = Callable[[torch.Tensor], torch.Tensor | None]


class PolicyRollout:
    """Rolls ``[*B, m]`` candidates ``h`` steps, sampling the actor at every imagined state.

    The same computation as the planners' step-by-step loop (actor parameters at each
    candidate's observation, one reparameterised draw per step, then the world model), run
    with less overhead: each candidate's state and action live side by side in one
    ``[N, state_dim + action_dim]`` buffer that is the model's input (no concatenation), the
    policy observation is a view of that buffer when the observation function returns one,
    the actor's linear layers are single ``addmm`` calls on its live weights and a
    state-independent scale is computed once per plan
    (:meth:`ActorSampler.tight_params`), and the model runs its folded layers
    (:meth:`CachedModelStep.layers`); a termination rule is applied to every imagined next
    state as the step-by-step loop applies it. It draws the same random numbers in the same
    order and runs the same floating-point operations on the same values, so its candidates, returns
    and chosen actions equal the step-by-step loop's.

    Args:
        model_step: the world model's cached step.
        sampler: the actor's sampler (a reparameterisable Normal or TanhNormal).
        observation: maps imagined states ``[N, state_dim]`` to the actor's observations
            (``None``: the actor reads the state).

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.envs import make_gym_state_env
        >>> from torchrl_mbmf.modules import DeltaDynamicsModel, make_ppo_actor_critic
        >>> from torchrl_mbmf.modules.planners import ActorSampler, CachedModelStep, PolicyRollout
        >>> actor, _ = make_ppo_actor_critic(make_gym_state_env("Pendulum-v1"))
        >>> rollout = PolicyRollout(
        ...     CachedModelStep(DeltaDynamicsModel(3, 1, hidden_sizes=(8,))),
        ...     ActorSampler(actor),
        ...     lambda state: None,
        ... )
        >>> rollout.available()
        True
        >>> first, rewards, final, ends = rollout(
        ...     torch.zeros(2, 3), num_candidates=15, horizon=10,
        ...     termination=lambda s: s[..., 0] > 0.5)
        >>> first.shape, rewards.shape, final.shape
        (torch.Size([2, 15, 1]), torch.Size([2, 15, 10]), torch.Size([2, 15, 3]))
        >>> ends.shape, ends.dtype
        (torch.Size([2, 15, 10]), torch.bool)
    """

    def __init__(
        self, model_step: CachedModelStep, sampler: ActorSampler, observation: ObservationFn
    ) -> None:
        self.model_step = model_step
        self.sampler = sampler
        self.observation = observation

    def available(self) -> bool:
        """Whether the model is a folded layer chain and the actor samples by reparameterising."""
        return self.sampler.tight_params() is not None and self.model_step.layers() is not None

    @torch.no_grad()
    def __call__(
        self,
        state: torch.Tensor,
        *,
        num_candidates: int,
        horizon: int,
        termination: Termination | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None] | None:
        """Rolls out the candidates of every real state (``None`` when not :meth:`available`).

        Args:
            state: real states ``[*B, state_dim]``.

        Keyword Args:
            num_candidates: ``m``.
            horizon: ``h``.
            termination: the terminal states' rule, applied to every imagined next state
                ``[N, state_dim]``, or ``None`` (the env never terminates). Defaults to
                ``None``.

        Returns:
            Every candidate's first action ``[*B, m, action_dim]``, its rewards
            ``[*B, m, h]``, its last state ``[*B, m, state_dim]`` and whether each step
            reached a terminal state ``[*B, m, h]`` (``None`` without ``termination``), or
            ``None``.
        """
        tight = self.sampler.tight_params()
        folded = self.model_step.layers()
        if tight is None or folded is None:
            return None
        params, _ = tight
        layers, d, last = folded.layers, folded.state_dim, folded.last
        if last is not None:
            layers = layers[:-1]
        batch = state.shape[:-1]
        n = batch.numel() * num_candidates
        x = state.new_empty(n, d + folded.action_dim)  # [state, action] of every candidate
        s, act = x[:, :d], x[:, d:]
        s.view(*batch, num_candidates, d).copy_(state.unsqueeze(-2))
        obs = self.observation(s)
        obs_is_view = obs is None or _shares_memory(obs, x)
        if obs is None:
            obs = s
        bounds = self.sampler.action_range()
        clip = (
            bounds is None or not folded.action_low <= bounds[0] <= bounds[1] <= folded.action_high
        )
        out = state.new_empty(horizon, n, d + 1)  # every step's [delta, reward]
        outs, deltas = out.unbind(0), out[:, :, :d].unbind(0)
        first = None
        ends = None if termination is None else state.new_zeros(horizon, n, dtype=torch.bool)
        sample = self.sampler.sample_params
        noise = state.new_empty(n, act.shape[-1])
        for t in range(horizon):
            if t and not obs_is_view:
                obs = self.observation(s)
            sample(*params(obs), out=act, noise=noise)
            if first is None:
                first = act.clone()
            if clip:
                act.clamp_(folded.action_low, folded.action_high)
            y = x
            for layer in layers:
                y = layer(y)
            if last is None:
                outs[t].copy_(y)
            else:
                torch.addmm(last[1], y, last[0], out=outs[t])
            s.add_(deltas[t])
            if ends is not None:
                ends[t] = termination(s)
        rewards = out[:, :, d].t().contiguous()
        shape = (*batch, num_candidates)
        terminated = None if ends is None else ends.t().contiguous().view(*shape, horizon)
        return (
            first.view(*shape, -1),
            rewards.view(*shape, horizon),
            s.clone().view(*shape, d),
            terminated,
        )


def _shares_memory(view: torch.Tensor, base: torch.Tensor) -> bool:
    return view.untyped_storage().data_ptr() == base.untyped_storage().data_ptr()
