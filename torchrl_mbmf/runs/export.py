"""The run folder's schema, shared by the trainers and the analysis.

Its name (the variant suffix of ``run_name``, :func:`variant_tag`, registered as the OmegaConf
resolver ``mbmf_variant``) and its trained policy (written beside every checkpoint by
:func:`save_policy`, loadable on its own by :func:`load_policy`).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch
from omegaconf import OmegaConf
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase

from torchrl_mbmf.envs.factory import make_env
from torchrl_mbmf.methods import PPO_METHODS
from torchrl_mbmf.modules.actors import make_ppo_actor_critic, make_sac_actor_critic
from torchrl_mbmf.runs.layout import CONFIG, POLICY

__all__ = ["POLICY_FILE", "load_policy", "save_policy", "variant_tag"]

#: File name of the exported policy inside a run folder.
POLICY_FILE = POLICY


def save_policy(actor: torch.nn.Module, run_dir: str | Path, step: int) -> Path:
    """Atomically writes the actor's weights and the real-step count to ``run_dir/policy.pt``.

    Args:
        actor: the policy module.
        run_dir: the run folder.
        step: real env steps the policy was trained on.

    Returns:
        The path written.

    Examples:
        >>> import tempfile, torch
        >>> from torchrl_mbmf.runs.export import save_policy
        >>> with tempfile.TemporaryDirectory() as d:
        ...     save_policy(torch.nn.Linear(2, 2), d, step=10).name
        'policy.pt'
    """
    path = Path(run_dir) / POLICY_FILE
    tmp = path.with_suffix(".pt.tmp")
    state = {name: t.detach().cpu() for name, t in actor.state_dict().items()}
    torch.save({"state_dict": state, "real_steps": int(step)}, tmp)
    os.replace(tmp, path)
    return path


def load_policy(
    run_dir: str | Path, env: EnvBase | None = None
) -> tuple[TensorDictModuleBase, EnvBase, dict[str, Any]]:
    """Rebuilds a run's actor from its ``config.yaml`` and loads ``policy.pt`` into it.

    Args:
        run_dir: a run folder written by ``recipes/train.py``.
        env: the env to build the actor for; by default a single env made from the run's
            config (env id, reward and its parameters, seed).

    Returns:
        ``(actor, env, info)``, where ``info`` holds ``real_steps`` and the run's config.

    Raises:
        FileNotFoundError: the folder has no ``config.yaml`` or ``policy.pt``.

    Examples:
        >>> from torchrl_mbmf.runs.export import load_policy
        >>> actor, env, info = load_policy("outputs/short/run")  # doctest: +SKIP
    """
    run_dir = Path(run_dir)
    for name in (CONFIG, POLICY_FILE):
        if not (run_dir / name).exists():
            raise FileNotFoundError(f"{run_dir} has no {name}; is it a finished training run?")
    cfg = OmegaConf.load(run_dir / CONFIG)
    if env is None:
        env = make_env(
            cfg.env.id,
            reward=cfg.reward.name,
            reward_kwargs=dict(cfg.reward.kwargs or {}),
            seed=int(cfg.seed),
        )
    if cfg.method in PPO_METHODS:
        actor, _ = make_ppo_actor_critic(
            env,
            hidden_sizes=tuple(cfg.ppo.hidden_sizes),
            distribution=cfg.ppo.distribution,
            init_log_std=float(cfg.ppo.init_log_std),
        )
    else:
        actor, _ = make_sac_actor_critic(env, hidden_sizes=tuple(cfg.sac.hidden_sizes))
    saved = torch.load(run_dir / POLICY_FILE, weights_only=True)
    actor.load_state_dict(saved["state_dict"])
    return actor, env, {"real_steps": int(saved["real_steps"]), "config": cfg}


def variant_tag(planner: Any, world_model: Any | None = None) -> str:
    """Run-name suffix naming the beyond-the-thesis options in use (empty for the thesis).

    Registered as the OmegaConf resolver ``mbmf_variant`` so that ``run_name`` separates the
    variants' run folders: ``${mbmf_variant:${planner},${world_model}}``.

    Args:
        planner: the ``planner`` config node (or dict).
        world_model: the ``world_model`` config node (or dict). Defaults to none.

    Returns:
        ``""`` for the thesis' settings, otherwise ``"__"`` and the options joined by ``-``.

    Examples:
        >>> from torchrl_mbmf.runs.export import variant_tag
        >>> variant_tag({"terminal_value": False, "refinement": None})
        ''
        >>> variant_tag({"terminal_value": True, "refinement": "cem"})
        '__value-cem'
    """
    parts = []
    if planner.get("terminal_value", False):
        parts.append("value")
    if planner.get("refinement"):
        parts.append(str(planner["refinement"]))
    wm = world_model or {}
    if int(wm.get("ensemble_size", 1) or 1) > 1:
        parts.append(f"ens{int(wm['ensemble_size'])}")
    if wm.get("adaptive_horizon", False):
        parts.append("adaptive")
    if int(wm.get("multi_step", 1) or 1) > 1:
        parts.append(f"ms{int(wm['multi_step'])}")
    return "__" + "-".join(parts) if parts else ""


OmegaConf.register_new_resolver("mbmf_variant", variant_tag, replace=True)
