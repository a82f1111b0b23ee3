"""Fast tensor-level sampling from a TorchRL stochastic actor, for planners."""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from tensordict.utils import NestedKey
from torch import distributions as D
from torch import nn
from torchrl.modules import IndependentNormal, TanhNormal

from torchrl_mbmf.modules.planners.actor_params import ParamsFn, TightParams, normal_log_prob


class ActorSampler:
    """Tensor-in, tensor-out view of a ``ProbabilisticActor`` for tight planning loops.

    Going through the actor's tensordict interface costs about 10x the network itself on a
    CPU. For the usual ``TensorDictModule(net, in_keys=[obs], out_keys=[loc, scale])`` and a
    :class:`~torchrl.modules.TanhNormal`, :class:`~torchrl.modules.IndependentNormal` or
    :class:`torch.distributions.Normal`, this samples by reparameterisation (same random
    numbers, same values as the distribution's ``sample``); other actors fall back on a
    tensordict pass and the distribution's ``sample``.

    Args:
        actor: a TorchRL ``ProbabilisticActor`` (any ``ProbabilisticTensorDictSequential``).

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.envs import make_gym_state_env
        >>> from torchrl_mbmf.modules import make_ppo_actor_critic
        >>> from torchrl_mbmf.modules.planners.sampling import ActorSampler
        >>> actor, _ = make_ppo_actor_critic(make_gym_state_env("Pendulum-v1"))
        >>> sampler = ActorSampler(actor)
        >>> sampler.sample(torch.zeros(15, 3)).shape
        torch.Size([15, 1])
    """

    def __init__(self, actor: TensorDictSequential) -> None:
        if not hasattr(actor, "get_dist") or not hasattr(actor, "dist_params_keys"):
            raise TypeError(
                f"the actor must be a stochastic TorchRL actor (a ProbabilisticActor with a "
                f"distribution); got {type(actor).__name__}, which has no get_dist"
            )
        self.actor = actor
        prob = actor.module[-1]
        self.distribution_class = prob.distribution_class
        self.distribution_kwargs = dict(prob.distribution_kwargs or {})
        self.param_keys: list[NestedKey] = list(actor.dist_params_keys)
        #: the key under which the actor writes its action's log-prob (losses read it)
        self.log_prob_key: NestedKey = getattr(prob, "log_prob_key", None) or "action_log_prob"
        params_modules = list(actor.module[:-1])
        in_keys = {k for m in params_modules for k in m.in_keys}
        in_keys -= {k for m in params_modules for k in m.out_keys}
        if len(in_keys) != 1:
            raise ValueError(
                f"the actor must read a single observation key, it reads {sorted(in_keys)}"
            )
        self.observation_key: NestedKey = in_keys.pop()
        self._net: nn.Module | None = None
        self._tight: TightParams | None = None
        self._params_fn = self._make_params_fn(params_modules)
        self._fast = self.distribution_class in (TanhNormal, IndependentNormal, D.Normal)
        if self.distribution_class is TanhNormal:
            low = torch.as_tensor(self.distribution_kwargs.get("low", -1.0))
            high = torch.as_tensor(self.distribution_kwargs.get("high", 1.0))
            self._tanh_loc = bool(self.distribution_kwargs.get("tanh_loc", False))
            self._upscale = self.distribution_kwargs.get("upscale", 5.0)
            self._mid, self._half = (high + low) / 2, (high - low) / 2
            self._affine = bool((high != 1.0).any() or (low != -1.0).any())
        # closed-form log-probs for exactly "Normal, then tanh (and the affine map to [low,
        # high])" or an independent Normal, as torchrl builds them
        kwargs = set(self.distribution_kwargs)
        if self.distribution_class is TanhNormal:
            self.closed_form_log_prob = kwargs <= {"low", "high", "tanh_loc", "upscale"}
            self.closed_form_log_prob &= not self._tanh_loc
        else:
            self.closed_form_log_prob = self.distribution_class is IndependentNormal and not kwargs

    def __getstate__(self) -> dict[str, object]:
        # closures over the network: rebuilt from the copied actor after a copy or pickle
        drop = ("_params_fn", "_tight")
        return {k: v for k, v in self.__dict__.items() if k not in drop}

    def __setstate__(self, state: dict[str, object]) -> None:
        self.__dict__.update(state)
        self._tight = None
        self._params_fn = self._make_params_fn(list(self.actor.module[:-1]))

    def _make_params_fn(
        self, modules: list[torch.nn.Module]
    ) -> Callable[[torch.Tensor], tuple[torch.Tensor, ...]]:
        if (
            len(modules) == 1
            and isinstance(modules[0], TensorDictModule)
            and list(modules[0].out_keys) == self.param_keys
            and isinstance(modules[0].module, torch.nn.Module)
        ):
            net = modules[0].module
            self._net = net
            return lambda obs: net(obs)
        seq = TensorDictSequential(*modules)
        key = self.observation_key

        def params(obs: torch.Tensor) -> tuple[torch.Tensor, ...]:
            td = seq(TensorDict({key: obs}, batch_size=obs.shape[:-1]))
            return tuple(td.get(k) for k in self.param_keys)

        return params

    def tight_params(self) -> tuple[ParamsFn, torch.Tensor | None] | None:
        """A tensor-only ``obs [N, d] -> (loc, scale)`` for the current weights, for hot loops.

        See :class:`~torchrl_mbmf.modules.planners.actor_params.TightParams`: ``None`` unless
        the parameter network is a plain chain and the distribution is sampled here.

        Returns:
            ``(params_fn, constant_scale)`` or ``None``.
        """
        if self._net is None or not self._fast:
            return None
        if self._tight is None:
            self._tight = TightParams(self._net)
        return self._tight()

    def sample_params(
        self,
        loc: torch.Tensor,
        scale: torch.Tensor,
        out: torch.Tensor | None = None,
        noise: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """One action per row of ``loc``, drawn as :meth:`sample` draws it (same numbers).

        Args:
            loc: the distribution's location ``[..., action_dim]`` (not modified).
            scale: its scale, any tensor broadcastable to ``loc``.
            out: where to write the actions (any strides). Defaults to a new tensor.
            noise: a buffer shaped like ``loc`` for the draw (the same numbers as a fresh
                one; used for a contiguous ``loc``). Defaults to a new tensor.
        """
        if noise is not None and loc.is_contiguous() and noise.shape == loc.shape:
            x = noise.normal_()  # what ``randn_like`` runs on its fresh tensor
        else:
            x = torch.randn_like(loc)  # (``torch.normal``: the same draw, slower: checks std)
        if self.distribution_class is not TanhNormal:
            if out is None:
                return x.mul_(scale).add_(loc)
            return torch.mul(x, scale, out=out).add_(loc)  # elementwise: the same values
        x.mul_(scale).add_(loc)
        x = x.tanh_() if out is None else torch.tanh(x, out=out)
        eps = torch.finfo(x.dtype).resolution
        x.clamp_(-1 + eps, 1 - eps)
        if self._affine:
            x.mul_(self._half.to(x)).add_(self._mid.to(x))
        return x

    def action_range(self) -> tuple[float, float] | None:
        """Bounds every action of :meth:`sample_params` lies in, or ``None`` (unbounded)."""
        if self.distribution_class is TanhNormal and not self._affine:
            return -1.0, 1.0
        return None

    def params(self, observation: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """The distribution parameters (``loc``, ``scale``) at ``observation``."""
        return tuple(self._params_fn(observation))

    def distribution(self, *params: torch.Tensor) -> D.Distribution:
        """The actor's distribution built from its parameters."""
        return self.distribution_class(*params, **self.distribution_kwargs)

    @property
    def is_fast(self) -> bool:
        """Whether actions are drawn tensor-level (TanhNormal, IndependentNormal, Normal)."""
        return self._fast

    def sample(self, observation: torch.Tensor) -> torch.Tensor:
        """Draws one action per observation (always random, whatever the exploration mode)."""
        return self.sample_with_params(observation)[0]

    def sample_with_params(
        self, observation: torch.Tensor
    ) -> tuple[torch.Tensor, tuple[torch.Tensor, ...]]:
        """Draws one action per observation and returns it with the distribution parameters.

        Args:
            observation: ``[*B, obs_dim]``.

        Returns:
            ``(action, params)``, ``params`` in the order of :attr:`param_keys`.

        Examples:
            >>> import torch
            >>> from torchrl_mbmf.envs import make_gym_state_env
            >>> from torchrl_mbmf.modules import make_ppo_actor_critic
            >>> from torchrl_mbmf.modules.planners.sampling import ActorSampler
            >>> actor, _ = make_ppo_actor_critic(make_gym_state_env("Pendulum-v1"))
            >>> ActorSampler(actor).sample_with_params(torch.zeros(3))[0].shape
            torch.Size([1])
        """
        # without autograd, the tight chain: the network's own ops on the same shape
        params = None if torch.is_grad_enabled() else self._tight_at(observation, flat=False)
        if params is None:
            params = tuple(self._params_fn(observation))
        return self._sample(params), params

    def sampler_for_fixed_weights(
        self,
    ) -> Callable[[torch.Tensor], tuple[torch.Tensor, tuple[torch.Tensor, ...]]]:
        """:meth:`sample_with_params` for a loop in which the actor's weights do not change.

        Without autograd the tight chain is looked up once here (not at every call): the
        returned function draws the same actions and returns the same ``loc`` and ``scale``
        values as :meth:`sample_with_params` while the weights stay as they were when it was
        made (a collector's batch: the policy is updated between batches). With autograd on,
        or without a tight chain, it is :meth:`sample_with_params` itself.

        Examples:
            >>> import torch
            >>> from torchrl_mbmf.envs import make_gym_state_env
            >>> from torchrl_mbmf.modules import make_ppo_actor_critic
            >>> from torchrl_mbmf.modules.planners.sampling import ActorSampler
            >>> actor, _ = make_ppo_actor_critic(make_gym_state_env("Pendulum-v1"))
            >>> with torch.no_grad():
            ...     draw = ActorSampler(actor).sampler_for_fixed_weights()
            ...     action, (loc, scale) = draw(torch.zeros(3))
            >>> action.shape, scale.shape
            (torch.Size([1]), torch.Size([1]))
        """
        tight = None if torch.is_grad_enabled() else self.tight_params()
        if tight is None:
            return self.sample_with_params
        fn, constant = tight
        sample = self._sample

        def draw(observation: torch.Tensor) -> tuple[torch.Tensor, tuple[torch.Tensor, ...]]:
            loc, scale = fn(observation)
            loc = loc.view(*observation.shape[:-1], loc.shape[-1])
            scale = constant.expand_as(loc) if constant is not None else scale.reshape(loc.shape)
            return sample((loc, scale)), (loc, scale)

        return draw

    def _sample(self, params: tuple[torch.Tensor, ...]) -> torch.Tensor:
        if not self._fast:
            return self.distribution(*params).sample()
        loc, scale = params
        if self.distribution_class is TanhNormal:
            if self._tanh_loc:
                loc = (loc / self._upscale).tanh() * self._upscale
            x = (loc + scale * torch.randn_like(loc)).tanh()
            eps = torch.finfo(x.dtype).resolution
            x = x.clamp(-1 + eps, 1 - eps)
            if self._affine:
                x = self._mid.to(x) + self._half.to(x) * x
            return x
        return loc + scale * torch.randn_like(loc)

    def log_prob(self, observation: torch.Tensor, action: torch.Tensor) -> dict[str, torch.Tensor]:
        """Distribution parameters at ``observation`` and the log-prob of ``action`` under them.

        In closed form where :attr:`closed_form_log_prob` (see
        :func:`~torchrl_mbmf.modules.planners.actor_params.normal_log_prob`).
        """
        params = self._tight_at(observation)
        if params is None:
            params = self._params_fn(observation)
        out = dict(zip(self.param_keys, params, strict=True))
        if self.closed_form_log_prob:
            out["log_prob"] = self.log_prob_params(action, *params)
        else:
            out["log_prob"] = self.distribution(*params).log_prob(action)
        return out

    def _tight_at(
        self, observation: torch.Tensor, flat: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor] | None:
        # (loc, scale) through the tight chain: the rows as one 2-d batch, or the own shape
        tight = self.tight_params()
        if tight is None:
            return None
        fn, constant = tight
        loc, scale = fn(observation.reshape(-1, observation.shape[-1]) if flat else observation)
        loc = loc.view(*observation.shape[:-1], loc.shape[-1])
        if constant is not None:  # a fresh tensor, as the network's own scale
            return loc, constant.expand_as(loc).clone()
        return loc, scale.reshape(loc.shape)

    def log_prob_params(
        self, action: torch.Tensor, loc: torch.Tensor, scale: torch.Tensor
    ) -> torch.Tensor:
        """Log-prob ``[...]`` of ``action`` under the distribution of ``loc`` and ``scale``.

        Closed form (see :meth:`log_prob`); falls back on the distribution's ``log_prob``.
        """
        if not self.closed_form_log_prob:
            return self.distribution(loc, scale).log_prob(action)
        squash = None
        if self.distribution_class is TanhNormal:
            squash = (self._mid, self._half) if self._affine else ()
        return normal_log_prob(action, loc, scale, squash)
