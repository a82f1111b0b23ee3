"""The run folder's schema, shared by the trainers and the analysis.

Its name (the variant suffix of ``run_name``, :func:`variant_tag`, registered as the OmegaConf
resolver ``mbmf_variant``) and its trained policy (written beside every checkpoint by
:func:`save_policy`, loadable on its own by :func:`load_policy`).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import pickle
import zipfile
from pathlib import Path
from typing import Any

import torch
from omegaconf import OmegaConf
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase

from torchrl_mbmf.envs.factory import make_env
from torchrl_mbmf.methods import PPO_METHODS
from torchrl_mbmf.modules.actors import make_ppo_actor_critic, make_sac_actor_critic
from torchrl_mbmf.runs.layout import CONFIG, POLICY, POLICY_RECORD
from torchrl_mbmf.runs.resume import IMPLIED_DEFAULTS

__all__ = [
    "POLICY_FILE",
    "CorruptPolicyError",
    "load_policy",
    "read_policy_state",
    "save_policy",
    "variant_tag",
]

#: File name of the exported policy inside a run folder.
POLICY_FILE = POLICY
_RECORD_FORMAT = "torchrl_mbmf.policy_integrity/1"
log = logging.getLogger(__name__)


class CorruptPolicyError(RuntimeError):
    """An exported policy does not match its integrity record, or cannot be read safely."""


def _sha256(path: Path) -> str:
    with path.open("rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def save_policy(actor: torch.nn.Module, run_dir: str | Path, step: int) -> Path:
    """Atomically writes the actor's weights and the real-step count to ``run_dir/policy.pt``.

    Its integrity record, ``policy.json`` (size and SHA-256 of ``policy.pt``, real steps), is
    written after it; :func:`load_policy` verifies it.

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
    record = Path(run_dir) / POLICY_RECORD
    tmp = path.with_suffix(".pt.tmp")
    state = {name: t.detach().cpu() for name, t in actor.state_dict().items()}
    torch.save({"state_dict": state, "real_steps": int(step)}, tmp)
    entry = {
        "format": _RECORD_FORMAT,
        "file": POLICY_FILE,
        "size": tmp.stat().st_size,
        "sha256": _sha256(tmp),
        "real_steps": int(step),
    }
    # The old record goes first: a crash between the two replaces leaves a policy without a
    # record (loaded with a warning), never a record that names other bytes.
    record.unlink(missing_ok=True)
    os.replace(tmp, path)
    record_tmp = record.with_suffix(".json.tmp")
    record_tmp.write_text(json.dumps(entry, indent=2) + "\n")
    os.replace(record_tmp, record)
    return path


def read_policy_state(run_dir: str | Path) -> tuple[dict[str, torch.Tensor], int]:
    """Reads and verifies ``policy.pt``: its integrity record, a pickle-free load, finite weights.

    Args:
        run_dir: the run folder.

    Returns:
        ``(state_dict, real_steps)``.

    Raises:
        FileNotFoundError: no ``policy.pt``.
        CorruptPolicyError: the file's size or SHA-256 differ from ``policy.json``, the file is
            truncated, a plain pickle or of another layout, or a weight is NaN or Inf. A policy
            exported before integrity records existed (no ``policy.json``) loads with a warning.

    Examples:
        >>> import tempfile, torch
        >>> from torchrl_mbmf.runs.export import read_policy_state, save_policy
        >>> with tempfile.TemporaryDirectory() as d:
        ...     _ = save_policy(torch.nn.Linear(2, 2), d, step=10)
        ...     state, steps = read_policy_state(d)
        >>> sorted(state), steps
        (['bias', 'weight'], 10)
    """
    path = Path(run_dir) / POLICY_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path} does not exist")
    record_path = Path(run_dir) / POLICY_RECORD
    if record_path.is_file():
        try:
            record = json.loads(record_path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as err:
            raise CorruptPolicyError(f"{record_path} is not valid JSON ({err})") from err
        if not isinstance(record, dict) or record.get("format") != _RECORD_FORMAT:
            raise CorruptPolicyError(f"{record_path} is not a {_RECORD_FORMAT} record")
        size = path.stat().st_size
        if size != record.get("size"):
            raise CorruptPolicyError(
                f"{path} has {size} bytes, its record {record_path.name} says {record.get('size')}"
                " (truncated or replaced)"
            )
        if _sha256(path) != record.get("sha256"):
            raise CorruptPolicyError(
                f"{path}'s SHA-256 differs from its record {record_path.name} (damaged or edited)"
            )
    else:
        log.warning("%s has no integrity record %s; loading it unverified", path, POLICY_RECORD)
    try:
        saved = torch.load(path, weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError, zipfile.BadZipFile) as err:
        raise CorruptPolicyError(
            f"{path} cannot be loaded as a policy export (truncated, damaged, or a pickle this "
            f"package never loads): {type(err).__name__}: {str(err).splitlines()[0][:200]}"
        ) from err
    state = saved.get("state_dict") if isinstance(saved, dict) else None
    steps = saved.get("real_steps") if isinstance(saved, dict) else None
    if not isinstance(state, dict) or not all(isinstance(t, torch.Tensor) for t in state.values()):
        raise CorruptPolicyError(f"{path} is not a policy export (no tensor 'state_dict')")
    if isinstance(steps, bool) or not isinstance(steps, int):
        raise CorruptPolicyError(f"{path} is not a policy export (no integer 'real_steps')")
    bad = [k for k, t in state.items() if t.is_floating_point() and not torch.isfinite(t).all()]
    if bad:
        raise CorruptPolicyError(f"{path} holds NaN or Inf weights in {bad}")
    return state, steps


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
        CorruptPolicyError: see :func:`read_policy_state`.

    Examples:
        >>> from torchrl_mbmf.runs.export import load_policy
        >>> actor, env, info = load_policy("outputs/short/run")  # doctest: +SKIP
    """
    run_dir = Path(run_dir)
    for name in (CONFIG, POLICY_FILE):
        if not (run_dir / name).exists():
            raise FileNotFoundError(f"{run_dir} has no {name}; is it a finished training run?")
    state, steps = read_policy_state(run_dir)  # verified before anything is built
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
        actor, _ = make_sac_actor_critic(
            env,
            hidden_sizes=tuple(cfg.sac.hidden_sizes),
            scale=str(cfg.sac.get("scale", IMPLIED_DEFAULTS["sac.scale"])),
        )
    actor.load_state_dict(state)
    return actor, env, {"real_steps": steps, "config": cfg}


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


def mbpo_tag(method: str, mbpo: Any, utd_ratio: float) -> str:
    """Run-name suffix of a ``sac_mbpo`` run's rollout and update settings (``""`` otherwise).

    Registered as the OmegaConf resolver ``mbpo_variant``:
    ``${mbpo_variant:${method},${mbpo},${sac.utd_ratio}}``.

    Args:
        method: the run's method.
        mbpo: the ``mbpo`` config node (or dict).
        utd_ratio: ``sac.utd_ratio``.

    Examples:
        >>> from torchrl_mbmf.runs.export import mbpo_tag
        >>> mbpo = {"rollout_horizon": 1, "rollout_batch_size": 25000, "real_ratio": 0.05,
        ...         "rollout_every": 250, "refit_every": 1000, "model_replay_size": 100000}
        >>> mbpo_tag("sac_mbpo", mbpo, 5), mbpo_tag("sac", mbpo, 1)
        ('__mbpo-H1-M25000-r0.05-utd5', '')
    """
    if method != "sac_mbpo":
        return ""
    utd = float(utd_ratio)
    parts = [
        f"H{int(mbpo['rollout_horizon'])}",
        f"M{int(mbpo['rollout_batch_size'])}",
        f"r{float(mbpo['real_ratio']):g}",
        f"utd{utd:g}",
    ]
    if int(mbpo["rollout_every"]) != 250:
        parts.append(f"every{int(mbpo['rollout_every'])}")
    if int(mbpo["refit_every"]) != 1000:
        parts.append(f"refit{int(mbpo['refit_every'])}")
    if int(mbpo["model_replay_size"]) != 100000:
        parts.append(f"keep{int(mbpo['model_replay_size'])}")
    return "__mbpo-" + "-".join(parts)


OmegaConf.register_new_resolver("mbmf_variant", variant_tag, replace=True)
OmegaConf.register_new_resolver("mbpo_variant", mbpo_tag, replace=True)
