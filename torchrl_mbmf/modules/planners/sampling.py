"""Fast tensor-level sampling from a TorchRL stochastic actor, for planners."""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from tensordict.utils import NestedKey
from torch import distributions as D
from torchrl.modules import IndependentNormal, TanhNormal


class ActorSampler:
    """Tensor-in, tensor-out view of a ``ProbabilisticActor`` for tight planning loops.

    A planner draws ``B x m`` actions per imagined step; going through the actor's tensordict
    interface (``actor.get_dist`` then ``sample``) costs about 10x the network itself on a CPU.
    This helper reaches the actor's parameter network directly when the actor is the usual
    ``TensorDictModule(net, in_keys=[obs], out_keys=[loc, scale])`` followed by the
    distribution, and samples :class:`~torchrl.modules.TanhNormal`,
    :class:`~torchrl.modules.IndependentNormal` and :class:`torch.distributions.Normal` with
    their reparameterisation (``loc + scale * randn``, then the tanh and affine maps), which
    draws the same random numbers and gives the same values as the distributions' own
    ``sample``. Other actors fall back on a tensordict pass and the distribution's ``sample``.

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
        params_modules = list(actor.module[:-1])
        in_keys = {k for m in params_modules for k in m.in_keys}
        in_keys -= {k for m in params_modules for k in m.out_keys}
        if len(in_keys) != 1:
            raise ValueError(
                f"the actor must read a single observation key, it reads {sorted(in_keys)}"
            )
        self.observation_key: NestedKey = in_keys.pop()
        self._params_fn = self._make_params_fn(params_modules)
        self._fast = self.distribution_class in (TanhNormal, IndependentNormal, D.Normal)
        if self.distribution_class is TanhNormal:
            low = torch.as_tensor(self.distribution_kwargs.get("low", -1.0))
            high = torch.as_tensor(self.distribution_kwargs.get("high", 1.0))
            self._tanh_loc = bool(self.distribution_kwargs.get("tanh_loc", False))
            self._upscale = self.distribution_kwargs.get("upscale", 5.0)
            self._mid, self._half = (high + low) / 2, (high - low) / 2
            self._affine = bool((high != 1.0).any() or (low != -1.0).any())

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
            return lambda obs: net(obs)
        seq = TensorDictSequential(*modules)
        key = self.observation_key

        def params(obs: torch.Tensor) -> tuple[torch.Tensor, ...]:
            td = seq(TensorDict({key: obs}, batch_size=obs.shape[:-1]))
            return tuple(td.get(k) for k in self.param_keys)

        return params

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
            >>> action, (loc, scale) = ActorSampler(actor).sample_with_params(torch.zeros(3))
            >>> action.shape, loc.shape
            (torch.Size([1]), torch.Size([1]))
        """
        params = tuple(self._params_fn(observation))
        return self._sample(params), params

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
        """Distribution parameters at ``observation`` and the log-prob of ``action`` under them."""
        params = self._params_fn(observation)
        out = dict(zip(self.param_keys, params, strict=True))
        out["log_prob"] = self.distribution(*params).log_prob(action)
        return out
