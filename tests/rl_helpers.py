"""Small losses and batches for the update tests and benchmarks (not part of the package).

The tests' ``conftest.py`` puts this folder on ``sys.path``; the benchmarks do the same.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.objectives import ClipPPOLoss, SACLoss
from torchrl.objectives.value import GAE

#: Overrides of ``recipes/train.py`` that make every method a few-second Pendulum run
#: (the recipe smoke tests and the pinned runs share them).
TINY_TRAIN = [
    "env=pendulum",
    "ppo.frames_per_batch=192",
    "planning_updates=2",
    "world_model.random_steps=300",
    "world_model.max_epochs=2",
    "world_model.hidden_sizes=[32,32]",
    "world_model.refit_every=1",
    "sac.frames_per_batch=100",
    "sac.init_random_frames=200",
    "sac.batch_size=32",
    "sac.hidden_sizes=[32,32]",
    "sac.refit_every_steps=300",
    "eval_every=400",
    "checkpoint.every_steps=400",
    "progress=false",
]

#: Overrides of a tiny HalfCheetah PPO-MPC run (the budget, ``total_steps``, is the caller's).
TINY_HALF_CHEETAH = [
    "method=ppo_mpc",
    "ppo.frames_per_batch=64",
    "ppo.minibatch_size=32",
    "planning_updates=2",
    "world_model.random_steps=150",
    "world_model.max_epochs=1",
    "world_model.hidden_sizes=[16]",
    "planner.horizon=3",
    "planner.num_candidates=4",
    "eval_every=100000",
    "eval_episodes=1",
    "checkpoint.every_steps=100000",
    "progress=false",
]


def build_for_checks(cfg, run_dir) -> None:
    """What a run checks before any work: the config, then every component built from it.

    ``recipes/train.py`` builds a :class:`~torchrl_mbmf.trainers.Trainer`; its constructor
    validates the config (the trainer's settings, key names, checks across keys) and builds
    the components of the config groups, whose constructors check their arguments.

    Args:
        cfg: the composed config.
        run_dir: a folder for the run (written only if everything is valid).
    """
    from torchrl_mbmf.trainers import Trainer

    Trainer(cfg, run_dir)


def make_test_sac_loss(
    batch_size: int = 8,
    obs_dim: int = 3,
    action_dim: int = 2,
    hidden: int = 16,
    activation: type[nn.Module] = nn.Tanh,
    loss_function: str = "smooth_l1",
    head: nn.Module | None = None,
) -> tuple[SACLoss, TensorDictBase]:
    """A small ``SACLoss`` and a random replay batch, for examples and tests.

    Args:
        batch_size: batch size. Defaults to 8.
        obs_dim: observation size. Defaults to 3.
        action_dim: action size. Defaults to 2.
        hidden: hidden width (two layers). Defaults to 16.
        activation: hidden activation of both networks. Defaults to :class:`torch.nn.Tanh`
            (``MLP``'s default; the training networks use :class:`torch.nn.ReLU`).
        loss_function: ``SACLoss``'s Q distance. Defaults to ``"smooth_l1"`` (its default).
        head: the actor's loc/scale head. Defaults to torchrl's ``NormalParamExtractor``.

    Returns:
        ``(loss, batch)``.

    Examples:
        >>> from rl_helpers import make_test_sac_loss
        >>> loss, batch = make_test_sac_loss(batch_size=4)
        >>> batch.batch_size
        torch.Size([4])
    """
    from tensordict import TensorDict
    from torchrl.data import Bounded
    from torchrl.modules import MLP, ProbabilisticActor, TanhNormal, ValueOperator

    spec = Bounded(-2.0, 2.0, (action_dim,))
    net = nn.Sequential(
        MLP(
            in_features=obs_dim,
            out_features=2 * action_dim,
            num_cells=[hidden, hidden],
            activation_class=activation,
        ),
        NormalParamExtractor(scale_mapping="biased_softplus_1.0", scale_lb=1e-4)
        if head is None
        else head,
    )
    actor = ProbabilisticActor(
        TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"]),
        in_keys=["loc", "scale"],
        spec=spec,
        distribution_class=TanhNormal,
        distribution_kwargs={"low": spec.space.low, "high": spec.space.high, "tanh_loc": False},
        return_log_prob=True,
    )
    qvalue = ValueOperator(
        MLP(
            in_features=obs_dim + action_dim,
            out_features=1,
            num_cells=[hidden, hidden],
            activation_class=activation,
        ),
        in_keys=["observation", "action"],
    )
    loss = SACLoss(actor, qvalue, num_qvalue_nets=2, action_spec=spec, loss_function=loss_function)
    loss.make_value_estimator(gamma=0.99)
    b = batch_size
    batch = TensorDict(
        {
            "observation": torch.randn(b, obs_dim),
            "action": torch.rand(b, action_dim) * 4 - 2,
            "next": {
                "observation": torch.randn(b, obs_dim),
                "reward": torch.randn(b, 1),
                "done": torch.rand(b, 1) < 0.2,
                "terminated": torch.rand(b, 1) < 0.2,
            },
        },
        batch_size=[b],
    )
    return loss, batch


def make_test_ppo(
    frames: int = 64,
    num_envs: int | None = None,
    obs_dim: int = 5,
    action_dim: int = 2,
    hidden: int = 16,
    distribution: str = "tanh_normal",
) -> tuple[ClipPPOLoss, GAE, TensorDictBase]:
    """A small ``ClipPPOLoss``, its ``GAE`` and a random rollout batch, for examples and tests.

    The batch carries done/terminated/truncated flags (about 5% each) and log-probabilities of
    its actions under the actor, as a collector batch does.

    Args:
        frames: time steps per env. Defaults to 64.
        num_envs: a leading env dimension (``[num_envs, frames]``), ``None`` for ``[frames]``.
        obs_dim: observation size. Defaults to 5.
        action_dim: action size (bounds ``[-1, 1]``). Defaults to 2.
        hidden: hidden width (two layers). Defaults to 16.
        distribution: ``"tanh_normal"`` or ``"normal"``, as in
            :func:`~torchrl_mbmf.modules.make_ppo_actor_critic`.

    Returns:
        ``(loss, gae, batch)``.

    Examples:
        >>> from rl_helpers import make_test_ppo
        >>> loss, gae, batch = make_test_ppo(frames=8, num_envs=2)
        >>> batch.batch_size
        torch.Size([2, 8])
    """
    from tensordict import TensorDict
    from torchrl.data import Bounded, Composite, Unbounded
    from torchrl.envs import EnvBase

    from torchrl_mbmf.modules import make_ppo_actor_critic

    class _SpecOnly(EnvBase):
        def __init__(self) -> None:
            super().__init__()
            self.observation_spec = Composite(observation=Unbounded((obs_dim,)))
            self.action_spec = Bounded(-1.0, 1.0, (action_dim,))
            self.reward_spec = Unbounded((1,))

        def _reset(self, tensordict):  # pragma: no cover - specs only
            raise NotImplementedError

        def _step(self, tensordict):  # pragma: no cover - specs only
            raise NotImplementedError

        def _set_seed(self, seed):  # pragma: no cover - specs only
            return seed

    actor, critic = make_ppo_actor_critic(
        _SpecOnly(), hidden_sizes=(hidden, hidden), distribution=distribution
    )
    loss = ClipPPOLoss(
        actor,
        critic,
        clip_epsilon=0.2,
        entropy_coeff=1e-4,
        critic_coeff=0.5,
        normalize_advantage=True,
    )
    gae = GAE(gamma=0.99, lmbda=0.95, value_network=critic, average_gae=False)
    shape = (frames,) if num_envs is None else (num_envs, frames)
    obs = torch.randn(*shape, obs_dim)
    next_obs = torch.cat([obs[..., 1:, :], torch.randn(*shape[:-1], 1, obs_dim)], -2)
    terminated = torch.rand(*shape, 1) < 0.05
    truncated = (torch.rand(*shape, 1) < 0.05) & ~terminated
    batch = TensorDict(
        {
            "observation": obs,
            "next": {
                "observation": next_obs,
                "reward": torch.randn(*shape, 1),
                "terminated": terminated,
                "truncated": truncated,
                "done": terminated | truncated,
            },
        },
        batch_size=shape,
    )
    with torch.no_grad():
        actor(batch)
    return loss, gae, batch
