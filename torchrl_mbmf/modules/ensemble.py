"""The ensemble's name for the one world-model network: ``K`` stacked thesis models."""

from __future__ import annotations

from typing import Any

from torchrl_mbmf.checks import check_number
from torchrl_mbmf.modules.dynamics import DeltaDynamicsModel
from torchrl_mbmf.modules.ensemble_layers import EnsembleLinear, FusedEnsembleStep


class EnsembleDeltaDynamicsModel(DeltaDynamicsModel):
    """:class:`~torchrl_mbmf.modules.DeltaDynamicsModel` with ``num_members`` members (5).

    The same network, scaling and methods: ``EnsembleDeltaDynamicsModel(s, a, num_members=K)``
    is ``DeltaDynamicsModel(s, a, ensemble_size=K)`` (same ``state_dict``, same outputs for a
    seed). For ``K >= 2`` each member has the thesis architecture
    (``state_dim + action_dim -> hidden_sizes -> state_dim + 1``, ReLU hidden layers, linear
    output) with stacked weights ``[K, in, out]``, all members run in one ``torch.baddbmm`` per
    layer, and ``forward`` (and :meth:`predict_scaled`, :meth:`fused_step`,
    ``as_tensordict_module``) give the members' mean, or one member per batch row with
    ``member_index``, so the ensemble is accepted wherever a ``DeltaDynamicsModel`` makes a
    prediction (:class:`~torchrl_mbmf.envs.LearnedDynamicsEnv` then steps the members' mean).
    Fit it with :func:`~torchrl_mbmf.world_model.ensemble_fit.fit_ensemble` (bootstrapped members),
    not ``fit_dynamics``; roll each batch element in its own member and read the disagreement
    with :class:`~torchrl_mbmf.envs.EnsembleLearnedDynamicsEnv`. ``num_members=1`` is the
    thesis model itself (its ``nn.Linear`` layout; an ensemble of one), fitted by
    ``fit_dynamics``.

    Args:
        state_dim: size of the state (18 for the thesis' HalfCheetah state).
        action_dim: size of the action (6 for HalfCheetah).

    Keyword Args:
        num_members: ensemble size ``K``. Defaults to ``5``.
        **kwargs: the other keywords of :class:`~torchrl_mbmf.modules.DeltaDynamicsModel`,
            with its defaults: ``hidden_sizes`` (of every member, ``(500, 500)``),
            ``activation`` (``nn.ReLU``), ``probabilistic`` (Gaussian members trained with
            the NLL, needs ``K >= 2``; ``False``), ``min_log_var`` (``-10.0``),
            ``max_log_var`` (``0.5``), ``action_low`` and ``action_high`` (``None``: no
            clip until a learned env sets its action spec).

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.modules import DeltaDynamicsModel, EnsembleDeltaDynamicsModel
        >>> _ = torch.manual_seed(0)
        >>> model = EnsembleDeltaDynamicsModel(18, 6, num_members=5, hidden_sizes=(32, 32))
        >>> _ = torch.manual_seed(0)
        >>> same = DeltaDynamicsModel(18, 6, ensemble_size=5, hidden_sizes=(32, 32))
        >>> s, a = torch.randn(4, 18), torch.rand(4, 6) * 2 - 1
        >>> torch.equal(model(s, a)[0], same(s, a)[0]), model.config == same.config
        (True, True)
    """

    def __init__(
        self, state_dim: int, action_dim: int, *, num_members: int = 5, **kwargs: Any
    ) -> None:
        k = check_number(num_members, "num_members", minimum=1, integer=True)
        super().__init__(state_dim, action_dim, ensemble_size=k, **kwargs)


def check_ensemble(model: object, name: str = "world_model") -> DeltaDynamicsModel:
    """Checks that ``model`` is an ensemble: a world model with ``ensemble_size >= 2``.

    Args:
        model: the model.
        name: the argument's name in the error message. Defaults to ``"world_model"``.

    Returns:
        ``model``.

    Raises:
        TypeError: naming the argument, the type and the ensemble size.

    Examples:
        >>> from torchrl_mbmf.modules import DeltaDynamicsModel
        >>> from torchrl_mbmf.modules.ensemble import check_ensemble
        >>> try:
        ...     check_ensemble(DeltaDynamicsModel(3, 1, hidden_sizes=(8,)))
        ... except TypeError as err:
        ...     print(err)
        world_model must be an ensemble of ensemble_size >= 2 members, such as an EnsembleDeltaDynamicsModel, got DeltaDynamicsModel with ensemble_size=1
    """  # noqa: E501
    size = getattr(model, "ensemble_size", None)
    if not isinstance(model, DeltaDynamicsModel) or size < 2:
        raise TypeError(
            f"{name} must be an ensemble of ensemble_size >= 2 members, such as an "
            f"EnsembleDeltaDynamicsModel, got {type(model).__name__}"
            + ("" if size is None else f" with ensemble_size={size}")
        )
    return model


__all__ = ["EnsembleDeltaDynamicsModel", "EnsembleLinear", "FusedEnsembleStep", "check_ensemble"]
