"""Fitting a learned termination head on a run's real transitions (``learn_termination``)."""

from __future__ import annotations

from torchrl_mbmf.data.transitions import TransitionDataset
from torchrl_mbmf.modules.termination import LearnedTermination, TerminationFit

__all__ = ["TERMINATION_EPOCHS", "fit_termination"]

#: Epochs of each fit of the head in a run (warm-started from the previous fit).
TERMINATION_EPOCHS = 20


def fit_termination(
    head: LearnedTermination,
    data: TransitionDataset,
    *,
    epochs: int = TERMINATION_EPOCHS,
    seed: int = 0,
) -> TerminationFit:
    """Fits ``head`` on every stored next state and the real env's ``terminated`` flag of it.

    The flags are the env's terminations alone: a time-limit truncation is not a terminal
    state. :meth:`~torchrl_mbmf.modules.LearnedTermination.fit` holds out a random split.

    Args:
        head: the termination head (its weights are the starting point).
        data: the real transitions; they must store ``terminated``.

    Keyword Args:
        epochs: passes over the training split. Defaults to :data:`TERMINATION_EPOCHS`.
        seed: seed of the split and the minibatch order. Defaults to ``0``.

    Returns:
        The held-out scores.

    Raises:
        ValueError: the dataset does not store ``terminated`` (saved by an older version).

    Examples:
        >>> from torchrl_mbmf.data import collect_random_transitions
        >>> from torchrl_mbmf.envs import make_env
        >>> from torchrl_mbmf.modules import LearnedTermination
        >>> from torchrl_mbmf.world_model.termination_fit import fit_termination
        >>> data = collect_random_transitions(make_env("Hopper-v5"), 300, seed=0)
        >>> fit = fit_termination(LearnedTermination(12, hidden_sizes=(16,)), data, epochs=2)
        >>> fit.val_size
        30
    """
    terminated = data.terminated()
    states = data.tensors().get(("next", data.state_key))
    return head.fit(states, terminated, epochs=epochs, seed=seed)
