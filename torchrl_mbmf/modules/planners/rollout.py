"""The one imagined rollout of the shooting planners, with pluggable candidate sources.

A rollout expands the real states into candidates and steps them ``h`` times in the world
model. Each step asks a *candidate source* for the candidates' actions (policy samples,
uniform draws, Gaussian action sequences, or a mixture of those) and a *transition* for
the next states, rewards and optionally the members' disagreement; an optional
:class:`TrustedHorizon` turns the disagreement into each candidate's trusted steps.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torchrl.envs.model_based import ModelBasedEnvBase

from torchrl_mbmf.modules.dynamics import DeltaDynamicsModel
from torchrl_mbmf.modules.ensemble_layers import FusedEnsembleStep
from torchrl_mbmf.modules.planners.stages import expand_candidates

#: ``source(states [*B, m, S], step) -> actions [*B, m, A]``.
CandidateSource = Callable[[torch.Tensor, int], torch.Tensor]
#: ``termination(states [*B, m, S]) -> terminated [*B, m]`` (bool).
Termination = Callable[[torch.Tensor], torch.Tensor]
#: ``transition(states, actions) -> (next_states, rewards [*B, m], disagreement or None)``.
Transition = Callable[
    [torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]
]

__all__ = [
    "CandidateSource",
    "ImaginedRollout",
    "MemberTransition",
    "SequenceMixture",
    "Termination",
    "Transition",
    "TrustedHorizon",
    "imagine",
    "learned_model",
    "model_transition",
]


def learned_model(env: object) -> DeltaDynamicsModel | None:
    """The world model of a learned env the planners can step as tensors, else ``None``.

    A learned env (such as :class:`~torchrl_mbmf.envs.LearnedDynamicsEnv`) exposes its
    ``dynamics`` (a :class:`~torchrl_mbmf.modules.DeltaDynamicsModel`), its ``state_key``, its
    ``observation_key``, ``observation(state)``, the policy observation of a state tensor, and
    ``terminated(state)``, its terminal states. Only an env whose ``steps_as_its_model()`` says
    its step is exactly that (no overridden ``_step``) qualifies: a
    :class:`~torchrl.envs.TransformedEnv` around it (a reward transform, say) or a subclass
    with its own step does not, and the planners then roll out through ``env.rollout``.

    Args:
        env: any env.

    Examples:
        >>> from torchrl_mbmf.envs import LearnedDynamicsEnv, make_gym_state_env
        >>> from torchrl_mbmf.modules import DeltaDynamicsModel
        >>> from torchrl_mbmf.modules.planners import learned_model
        >>> real = make_gym_state_env("Pendulum-v1")
        >>> env = LearnedDynamicsEnv(DeltaDynamicsModel(3, 1, hidden_sizes=(8,)), real)
        >>> learned_model(env) is env.dynamics, learned_model(real)
        (True, None)
    """
    if not isinstance(env, ModelBasedEnvBase):  # a TransformedEnv forwards attributes
        return None
    check = getattr(env, "steps_as_its_model", None)
    if not callable(check) or not check():
        return None
    model = getattr(env, "dynamics", None)
    steppable = callable(getattr(env, "observation", None)) and hasattr(env, "state_key")
    return model if isinstance(model, DeltaDynamicsModel) and steppable else None


@dataclass
class ImaginedRollout:
    """What one rollout of ``[*B, m]`` candidates over ``h`` imagined steps produced.

    Attributes:
        first_actions: every candidate's first action ``[*B, m, A]``.
        rewards: imagined rewards ``[*B, m, h]``.
        final_state: every candidate's last state ``[*B, m, S]`` (its last trusted state
            with a :class:`TrustedHorizon`).
        actions: every candidate's actions ``[*B, m, h, A]``, when they were kept.
        trusted_steps: trusted steps ``[*B, m]`` (with a :class:`TrustedHorizon`).
        disagreement: the transition's disagreement ``[*B, m, h]``, when it reports one.
        terminated: whether each imagined step reached a terminal state ``[*B, m, h]``
            (bool), when the learned env can terminate.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.modules.planners import ImaginedRollout
        >>> ImaginedRollout(torch.zeros(1, 2, 1), torch.ones(1, 2, 3), torch.zeros(1, 2, 4)).actions
    """

    first_actions: torch.Tensor
    rewards: torch.Tensor
    final_state: torch.Tensor
    actions: torch.Tensor | None = None
    trusted_steps: torch.Tensor | None = None
    disagreement: torch.Tensor | None = None
    terminated: torch.Tensor | None = None


class TrustedHorizon:
    """The adaptive-horizon mask: a candidate is trusted until its first too-uncertain step.

    A candidate's trusted steps ``T`` end at its first imagined step whose disagreement
    exceeds ``threshold``; its last trusted state is the state before that step (the real
    state when ``T = 0``). With ``threshold=None`` every candidate keeps the whole horizon.

    Args:
        threshold: the disagreement threshold, or ``None``.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.modules.planners.rollout import TrustedHorizon
        >>> mask = TrustedHorizon(0.5)
        >>> mask.start(torch.zeros(2, 1))
        >>> for t, d in enumerate([[0.1, 0.9], [0.2, 0.1]]):
        ...     mask.update(torch.full((2, 1), t + 1.0), torch.tensor(d))
        >>> steps, last = mask.finish(torch.full((2, 1), 2.0), horizon=2)
        >>> steps, last[:, 0]
        (tensor([2, 0]), tensor([2., 0.]))
    """

    def __init__(self, threshold: float | None) -> None:
        self.threshold = threshold

    def start(self, state: torch.Tensor) -> None:
        """Starts a rollout from the candidates' states ``[*B, m, S]``."""
        shape = state.shape[:-1]
        self.trusted = torch.zeros(shape, dtype=torch.long, device=state.device)
        self.alive = torch.ones(shape, dtype=torch.bool, device=state.device)
        self.last = state

    def update(self, state: torch.Tensor, disagreement: torch.Tensor) -> None:
        """Counts an imagined step reaching ``state`` with the step's ``disagreement``."""
        if self.threshold is None:
            return
        self.alive = self.alive & (disagreement <= self.threshold)
        self.trusted += self.alive
        self.last = torch.where(self.alive.unsqueeze(-1), state, self.last)

    def finish(self, state: torch.Tensor, horizon: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Trusted steps ``[*B, m]`` and last trusted states ``[*B, m, S]``."""
        if self.threshold is None:
            return self.trusted.fill_(horizon), state
        return self.trusted, self.last


class SequenceMixture:
    """A candidate source: the first candidates from ``policy``, the rest follow sequences.

    Args:
        policy: the source of the first ``m - n`` candidates (closed loop).
        sequences: open-loop action sequences ``[*B, n, h, A]`` of the last ``n``.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.modules.planners.rollout import SequenceMixture
        >>> source = SequenceMixture(lambda s, t: s.new_zeros(*s.shape[:-1], 1),
        ...                          torch.ones(1, 2, 4, 1))
        >>> source(torch.zeros(1, 5, 3), 0)[0, :, 0]
        tensor([0., 0., 0., 1., 1.])
    """

    def __init__(self, policy: CandidateSource, sequences: torch.Tensor) -> None:
        self.policy = policy
        self.sequences = sequences

    def __call__(self, state: torch.Tensor, step: int) -> torch.Tensor:
        """Actions ``[*B, m, A]`` of imagined ``step``."""
        n_policy = state.shape[-2] - self.sequences.shape[-3]
        if not n_policy:
            return self.sequences[..., step, :]
        sampled = self.policy(state[..., :n_policy, :], step)
        return torch.cat([sampled, self.sequences[..., step, :]], dim=-2)


def model_transition(
    predict: Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]],
) -> Transition:
    """The transition of a world model's ``predict(s, a) -> (s', r [..., 1])`` (no disagreement).

    Args:
        predict: the model's tensor step (such as a cached folded step).

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.modules.planners.rollout import model_transition
        >>> step = model_transition(lambda s, a: (s + a, a.sum(-1, keepdim=True)))
        >>> step(torch.zeros(2, 1), torch.ones(2, 1))
        (tensor([[1.],
                [1.]]), tensor([1., 1.]), None)
    """

    def transition(state: torch.Tensor, action: torch.Tensor):
        next_state, reward = predict(state, action)
        return next_state, reward[..., 0], None

    return transition


class MemberTransition:
    """The transition of an ensemble: candidate ``i`` is stepped by member ``i mod K``.

    With ``disagreement=True`` every member runs on every candidate (``K`` times one model's
    FLOPs) and the step reports the members' disagreement; otherwise each candidate goes
    through its own member only. Both give the same states and rewards.

    Args:
        fused: the ensemble's folded kernel.
        disagreement: report the disagreement.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.modules import EnsembleDeltaDynamicsModel
        >>> from torchrl_mbmf.modules.planners.rollout import MemberTransition
        >>> model = EnsembleDeltaDynamicsModel(3, 1, num_members=2, hidden_sizes=(8,))
        >>> fused = model.fused_members()
        >>> s, a = torch.randn(4, 6, 3), torch.randn(4, 6, 1)
        >>> full, own = MemberTransition(fused, True)(s, a), MemberTransition(fused, False)(s, a)
        >>> torch.allclose(full[0], own[0], atol=1e-5), full[2].shape, own[2]
        (True, torch.Size([4, 6]), None)
    """

    def __init__(self, fused: FusedEnsembleStep, disagreement: bool) -> None:
        self.fused = fused
        self.track = disagreement
        self.own_member: torch.Tensor | None = None

    def _own_member(self, shape: torch.Size, device: torch.device) -> torch.Tensor:
        """Gather index ``[1, *B, m, S + 1]`` picking member ``i mod K`` for candidate ``i``."""
        if self.own_member is None or self.own_member.shape[1:] != shape[1:]:
            k, m = shape[0], shape[-2]
            member = torch.arange(m, device=device) % k
            member = member.view(1, *([1] * (len(shape) - 3)), m, 1)
            self.own_member = member.expand(1, *shape[1:])
        return self.own_member

    def __call__(self, state: torch.Tensor, action: torch.Tensor):
        """``(next_states, rewards, disagreement or None)`` of one imagined step."""
        d = self.fused.state_dim
        disagreement = None
        if self.track:
            out = self.fused.members(state, action)  # [K, *B, m, S + 1]
            disagreement = self.fused.disagreement(out)
            out = out.gather(0, self._own_member(out.shape, out.device)).squeeze(0)
        else:
            out = self.fused.cyclic(state, action)
        return state + out[..., :d], out[..., d], disagreement


def imagine(
    state: torch.Tensor,
    *,
    num_candidates: int,
    horizon: int,
    source: CandidateSource,
    transition: Transition,
    trust: TrustedHorizon | None = None,
    keep_actions: bool = False,
    termination: Termination | None = None,
) -> ImaginedRollout:
    """Expands the real states into candidates and rolls them ``horizon`` imagined steps.

    Args:
        state: real states ``[*B, S]``.

    Keyword Args:
        num_candidates: ``m``.
        horizon: ``h``.
        source: the candidates' actions at each step.
        transition: the world model's step.
        trust: the adaptive-horizon mask (needs a transition reporting disagreement).
            Defaults to none.
        keep_actions: keep every step's actions (for refitting a sampling distribution).
            Defaults to ``False``.
        termination: the terminal states' rule, applied to every imagined next state, or
            ``None`` when the env never terminates. Defaults to ``None``.

    Returns:
        The :class:`ImaginedRollout`.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.modules.planners.rollout import imagine, model_transition
        >>> out = imagine(torch.zeros(2, 3), num_candidates=4, horizon=5,
        ...               source=lambda s, t: s.new_ones(*s.shape[:-1], 3),
        ...               transition=model_transition(lambda s, a: (s + a, a[..., :1])))
        >>> out.rewards.shape, out.final_state[0, 0]
        (torch.Size([2, 4, 5]), tensor([5., 5., 5.]))
    """
    s = expand_candidates(state, num_candidates)
    rewards = s.new_empty(*s.shape[:-1], horizon)
    actions = disagreement = first = None
    terminated = None
    if termination is not None:
        terminated = torch.zeros(rewards.shape, dtype=torch.bool, device=s.device)
    if trust is not None:
        trust.start(s)
    for t in range(horizon):
        a = source(s, t)
        if first is None:
            first = a
            if keep_actions:
                actions = a.new_empty(*a.shape[:-1], horizon, a.shape[-1])
        if actions is not None:
            actions[..., t, :] = a
        s, r, d = transition(s, a)
        rewards[..., t] = r
        if terminated is not None:
            terminated[..., t] = termination(s)
        if d is not None:
            if disagreement is None:
                disagreement = s.new_empty(*s.shape[:-1], horizon)
            disagreement[..., t] = d
        if trust is not None:
            trust.update(s, d)
    out = ImaginedRollout(
        first, rewards, s, actions, disagreement=disagreement, terminated=terminated
    )
    if trust is not None:
        out.trusted_steps, out.final_state = trust.finish(s, horizon)
    return out
