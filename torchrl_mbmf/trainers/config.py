"""Validation of the training config: fail before any work starts, naming the key."""

from __future__ import annotations

from typing import Any

from omegaconf import OmegaConf

from torchrl_mbmf.envs.transforms.rewards import REWARDS

#: Methods of ``recipes/train.py``.
METHODS: tuple[str, ...] = ("ppo", "mpc", "ppo_mpc", "sac", "sac_mpc")
#: Methods that plan with a learned model.
MODEL_BASED: tuple[str, ...] = ("mpc", "ppo_mpc", "sac_mpc")
#: Methods trained with PPO.
PPO_METHODS: tuple[str, ...] = ("ppo", "mpc", "ppo_mpc")
SAC_UPDATES: tuple[str, ...] = ("fused", "stock")
COLLECTORS: tuple[str, ...] = ("lean", "stock")
PPO_UPDATES: tuple[str, ...] = ("fused", "fused_autograd", "stock")
LOGGERS: tuple[str, ...] = ("csv", "tensorboard", "wandb", "mlflow", "")
REFINEMENTS: tuple[str | None, ...] = (None, "cem", "mppi")


class ConfigError(ValueError):
    """A training config value is invalid; the message names the key and the allowed values."""


def _positive(cfg: Any, key: str) -> None:
    node = cfg
    for part in key.split("."):
        node = node[part]
    if not isinstance(node, int | float) or isinstance(node, bool) or node < 1:
        raise ConfigError(f"{key} must be a number >= 1, got {node!r}")


def validate_train_config(cfg: Any) -> None:
    """Checks a composed ``train`` config before anything is built.

    Args:
        cfg: the composed config (an OmegaConf ``DictConfig`` or a nested dict).

    Raises:
        ConfigError: naming the offending key and the allowed values.

    Examples:
        >>> from torchrl_mbmf.trainers.config import ConfigError, validate_train_config
        >>> try:
        ...     validate_train_config({"method": "dqn"})
        ... except ConfigError as err:
        ...     print(err)
        method='dqn' is not a method; allowed: ['ppo', 'mpc', 'ppo_mpc', 'sac', 'sac_mpc']
    """
    method = cfg["method"]
    if method not in METHODS:
        raise ConfigError(f"method={method!r} is not a method; allowed: {list(METHODS)}")
    reward = cfg["reward"]["name"]
    if reward not in REWARDS:
        raise ConfigError(f"reward.name={reward!r} is not a reward; allowed: {sorted(REWARDS)}")
    if cfg["logger"]["backend"] not in LOGGERS:
        raise ConfigError(
            f"logger.backend={cfg['logger']['backend']!r} is not supported; allowed: "
            f"{list(LOGGERS)}"
        )
    if cfg["sac"].get("update", "stock") not in SAC_UPDATES:
        raise ConfigError(
            f"sac.update={cfg['sac']['update']!r} is not supported; allowed: {list(SAC_UPDATES)}"
        )
    if cfg["ppo"].get("update", "stock") not in PPO_UPDATES:
        raise ConfigError(
            f"ppo.update={cfg['ppo']['update']!r} is not supported; allowed: {list(PPO_UPDATES)}"
        )
    if cfg.get("collector", "lean") not in COLLECTORS:
        raise ConfigError(
            f"collector={cfg['collector']!r} is not supported; allowed: {list(COLLECTORS)}"
        )
    for key in (
        "total_steps",
        "env.num_envs",
        "planner.num_candidates",
        "planner.horizon",
        "world_model.random_steps",
        "world_model.refit_every",
        "world_model.max_epochs",
        "world_model.batch_size",
        "eval_every",
        "checkpoint.every_steps",
        "checkpoint.keep_last",
        "ppo.frames_per_batch",
        "ppo.minibatch_size",
        "ppo.epochs",
        "sac.frames_per_batch",
        "sac.batch_size",
        "sac.refit_every_steps",
    ):
        _positive(cfg, key)
    if not 0 < cfg["planner"]["discount"] <= 1:
        raise ConfigError(f"planner.discount must be in (0, 1], got {cfg['planner']['discount']}")
    _check_planner_variants(cfg, method)
    _check_world_model_variants(cfg, method)
    n_envs = int(cfg["env"]["num_envs"])
    algo = "ppo" if method in PPO_METHODS else "sac"
    frames = int(cfg[algo]["frames_per_batch"])
    if frames % n_envs:
        raise ConfigError(
            f"{algo}.frames_per_batch={frames} must be a multiple of env.num_envs={n_envs}"
        )
    if method in PPO_METHODS and frames % int(cfg["ppo"]["minibatch_size"]):
        raise ConfigError(
            f"ppo.frames_per_batch={frames} must be a multiple of "
            f"ppo.minibatch_size={cfg['ppo']['minibatch_size']}"
        )
    total = int(cfg["total_steps"])
    if method in ("mpc", "ppo_mpc"):
        updates = int(cfg["planning_updates"])
        if updates < 0:
            raise ConfigError(f"planning_updates must be >= 0, got {updates}")
        needed = int(cfg["world_model"]["random_steps"]) + updates * frames
        if needed > total:
            raise ConfigError(
                f"planning_updates={updates} needs world_model.random_steps + planning_updates "
                f"x ppo.frames_per_batch = {needed} real steps, beyond total_steps={total}"
            )
    if method in MODEL_BASED and int(cfg["world_model"]["random_steps"]) >= total:
        raise ConfigError(
            f"world_model.random_steps={cfg['world_model']['random_steps']} leaves no steps "
            f"of total_steps={total} for training"
        )


def _check_planner_variants(cfg: Any, method: str) -> None:
    planner = cfg["planner"]
    value = planner.get("terminal_value", False)
    if not isinstance(value, bool):
        raise ConfigError(f"planner.terminal_value must be true or false, got {value!r}")
    refinement = planner.get("refinement")
    if refinement not in REFINEMENTS:
        raise ConfigError(
            f"planner.refinement={refinement!r} is not supported; allowed: {list(REFINEMENTS)}"
        )
    if refinement is None:
        return
    if method not in ("ppo_mpc", "sac_mpc"):
        raise ConfigError(
            f"planner.refinement={refinement!r} refines around the policy prior; it needs "
            f"method ppo_mpc or sac_mpc, got method={method!r}"
        )
    _positive(cfg, "planner.iterations")
    elites, m = planner["num_elites"], planner["num_candidates"]
    if not isinstance(elites, int) or not 1 <= elites <= m:
        raise ConfigError(
            f"planner.num_elites must be an integer in [1, planner.num_candidates={m}], "
            f"got {elites!r}"
        )
    if not 0 <= planner["policy_fraction"] < 1:
        raise ConfigError(
            f"planner.policy_fraction must be in [0, 1), got {planner['policy_fraction']!r}"
        )
    if planner["temperature"] <= 0:
        raise ConfigError(f"planner.temperature must be > 0, got {planner['temperature']!r}")
    if planner["min_std"] < 0:
        raise ConfigError(f"planner.min_std must be >= 0, got {planner['min_std']!r}")


def _check_world_model_variants(cfg: Any, method: str) -> None:
    from torchrl_mbmf.trainers.dynamics import fit_dynamics_kwargs

    wm = cfg["world_model"]
    try:
        kwargs = fit_dynamics_kwargs(wm)
    except (TypeError, ValueError) as err:
        raise ConfigError(str(err)) from err
    members = wm.get("ensemble_size", 1)
    if isinstance(members, bool) or not isinstance(members, int) or members < 1:
        raise ConfigError(f"world_model.ensemble_size must be an integer >= 1, got {members!r}")
    adaptive = wm.get("adaptive_horizon", False)
    if not isinstance(adaptive, bool):
        raise ConfigError(f"world_model.adaptive_horizon must be true or false, got {adaptive!r}")
    if members > 1 and method not in ("ppo_mpc", "sac_mpc"):
        raise ConfigError(
            f"world_model.ensemble_size={members} plans with the ensemble policy-guided planner; "
            f"it needs method ppo_mpc or sac_mpc, got method={method!r}"
        )
    if members > 1 and cfg["planner"].get("refinement"):
        raise ConfigError(
            "planner.refinement is not supported with world_model.ensemble_size > 1; set one "
            "of them back (planner.refinement=null or world_model.ensemble_size=1)"
        )
    if members > 1 and kwargs["multi_step"] > 1:
        raise ConfigError(
            "world_model.multi_step > 1 is implemented for the single model only; set "
            "world_model.ensemble_size=1 or world_model.multi_step=1"
        )
    if adaptive and members < 2:
        raise ConfigError(
            "world_model.adaptive_horizon needs an ensemble (world_model.ensemble_size >= 2), "
            f"got ensemble_size={members}"
        )
    if adaptive and not 0 < wm.get("disagreement_quantile", 0.9) < 1:
        raise ConfigError(
            "world_model.disagreement_quantile must be in (0, 1), got "
            f"{wm.get('disagreement_quantile')!r}"
        )


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
        >>> from torchrl_mbmf.trainers.config import variant_tag
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
