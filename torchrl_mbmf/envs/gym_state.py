"""Factory for gymnasium envs exposing a model state and a policy observation."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import gymnasium as gym
import torch
from torchrl._utils import set_auto_unwrap_transformed_env
from torchrl.data import Unbounded
from torchrl.envs import (
    Compose,
    DoubleToFloat,
    GymWrapper,
    RenameTransform,
    RewardSum,
    StepCounter,
    Transform,
    TransformedEnv,
)
from torchrl.envs.libs.gym import default_info_dict_reader

from torchrl_mbmf.envs.keys import OBSERVATION_KEY, STATE_KEY
from torchrl_mbmf.envs.physics_info import quiet_mujoco_warnings
from torchrl_mbmf.envs.tasks import task_layout
from torchrl_mbmf.envs.transforms.observation import StateToObservation


def make_gym_state_env(
    env_id: str,
    *,
    num_envs: int = 1,
    seed: int | None = None,
    device: str | torch.device = "cpu",
    drop_state_dims: Sequence[int] | None = None,
    info_specs: Mapping[str, Sequence[int]] | None = None,
    wrap: Callable[[gym.Env], gym.Env] | None = None,
    transforms: Sequence[Transform] = (),
    state_key: str = STATE_KEY,
    observation_key: str = OBSERVATION_KEY,
    layout: bool = True,
    **gym_kwargs: Any,
) -> TransformedEnv:
    """Builds a TorchRL env on a gymnasium env with a vector observation and continuous actions.

    The gymnasium observation becomes the model ``state`` (float32); the policy ``observation`` is
    that state with ``drop_state_dims`` removed (:class:`StateToObservation`). A task of
    :data:`~torchrl_mbmf.envs.tasks.TASK_LAYOUTS` gets its layout, as in the recipes
    (:func:`~torchrl_mbmf.envs.make_env`): the state with the root's x (and y) position first
    (``exclude_current_positions_from_observation=False`` for the MuJoCo locomotion tasks) and
    the policy observation without them; ``layout=False`` keeps Gymnasium's own observation.
    Info entries named in ``info_specs`` are read into the tensordict. ``transforms`` (for
    example a reward transform) come next, then :class:`~torchrl.envs.StepCounter` and
    :class:`~torchrl.envs.RewardSum` (``episode_reward``), so the tracked return is the one the
    transforms define.

    ``num_envs > 1`` runs the copies in one gymnasium ``SyncVectorEnv`` (same-step auto-reset)
    inside a single TorchRL wrapper: on a few cores this is much cheaper than one process or one
    TorchRL env per copy. Keys and specs are the same, with a leading ``[num_envs]`` batch dim.

    Args:
        env_id: gymnasium id, for example ``"Pendulum-v1"``.

    Keyword Args:
        num_envs: number of copies stepped together. Defaults to ``1`` (an unbatched env).
        seed: seed of the env (copy ``i`` gets ``seed + i``), or ``None``. Defaults to ``None``.
        device: device of the returned tensors. Defaults to ``"cpu"``.
        drop_state_dims: state dims hidden from the policy observation. Defaults to the task
            layout's (the positions), ``()`` without one.
        info_specs: info key -> per-env shape of float entries to read. Defaults to none.
        wrap: function applied to each gymnasium env after ``gym.make``. Defaults to none.
        transforms: transforms inserted before the step counter and return tracker.
        state_key: key of the model state. Defaults to :data:`~torchrl_mbmf.envs.STATE_KEY`.
        observation_key: key of the policy observation. Defaults to
            :data:`~torchrl_mbmf.envs.OBSERVATION_KEY`.
        layout: apply the task's layout (:func:`~torchrl_mbmf.envs.task_layout`). Defaults to
            ``True``.
        **gym_kwargs: passed to ``gym.make``.

    Returns:
        A :class:`~torchrl.envs.TransformedEnv`.

    Raises:
        ValueError: ``num_envs < 1``, ``state_key == observation_key``, or (with ``layout``) a
            ``gym_kwargs`` entry that would take the positions out of the task's state.

    Examples:
        >>> from torchrl.envs.utils import check_env_specs
        >>> from torchrl_mbmf.envs import make_gym_state_env
        >>> env = make_gym_state_env("Pendulum-v1", seed=0)
        >>> check_env_specs(env)
        >>> env.rollout(3)["next", "observation"].shape
        torch.Size([3, 3])
        >>> hopper = make_gym_state_env("Hopper-v5").rollout(2)  # x first, hidden from the policy
        >>> hopper["state"].shape, hopper["observation"].shape
        (torch.Size([2, 12]), torch.Size([2, 11]))
    """
    if num_envs < 1:
        raise ValueError(f"num_envs must be >= 1, got {num_envs}")
    if state_key == observation_key:
        raise ValueError(
            f"state_key and observation_key must differ (both {state_key!r}): the policy "
            "observation is written from the state under its own key"
        )

    known = task_layout(env_id) if layout else None
    if known is not None:
        try:
            gym_kwargs = known.make_kwargs(gym_kwargs)
        except ValueError as err:
            raise ValueError(f"{err}; pass layout=False for Gymnasium's own observation") from err
    if drop_state_dims is None:
        drop_state_dims = () if known is None else known.hidden_dims

    def make_one() -> gym.Env:
        with quiet_mujoco_warnings():
            env = gym.make(env_id, **gym_kwargs)
        return wrap(env) if wrap is not None else env

    if num_envs == 1:
        gym_env: gym.Env = make_one()
        batch: tuple[int, ...] = ()
    else:
        gym_env = gym.vector.SyncVectorEnv(
            [make_one] * num_envs, autoreset_mode=gym.vector.AutoresetMode.SAME_STEP
        )
        batch = (num_envs,)
    base = GymWrapper(gym_env, device=device)
    if info_specs:
        keys = list(info_specs)
        specs = [Unbounded(shape=(*batch, *info_specs[k]), dtype=torch.float64) for k in keys]
        base.set_info_dict_reader(default_info_dict_reader(keys, spec=specs))
    state_dim = base.observation_spec["observation"].shape[-1]
    chain: list[Transform] = [DoubleToFloat()]
    if state_key != "observation":
        chain.append(RenameTransform(in_keys=["observation"], out_keys=[state_key]))
    chain.append(
        StateToObservation(
            state_dim, drop_dims=drop_state_dims, in_key=state_key, out_key=observation_key
        )
    )
    chain.extend(transforms)
    chain.extend([StepCounter(), RewardSum()])
    with set_auto_unwrap_transformed_env(True):
        # a vector env comes back as TransformedEnv(auto-reset handler): extend that chain
        env = TransformedEnv(base, Compose(*chain))
    if seed is not None:
        env.set_seed(seed)
    return env
