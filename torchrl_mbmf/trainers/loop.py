"""The training loop of every method: model-free, MBMF planning phase, warm-start fine-tuning."""

from __future__ import annotations

import hashlib
import json
import logging
import os
import random
import subprocess
import time
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import OmegaConf
from tensordict import TensorDictBase
from torchrl.checkpoint import CheckpointRotation, GlobalRNGState, JSONCheckpointAdapter
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, RandomPolicy, set_exploration_type
from torchrl.objectives import ClipPPOLoss, SACLoss, SoftUpdate
from torchrl.objectives.value import GAE
from torchrl.record.loggers import CSVLogger, get_logger
from tqdm.auto import tqdm

from torchrl_mbmf.collectors import LeanCollector
from torchrl_mbmf.data.transitions import TransitionDataset
from torchrl_mbmf.envs.ensemble_env import EnsembleLearnedDynamicsEnv
from torchrl_mbmf.envs.factory import env_metadata, make_env
from torchrl_mbmf.envs.keys import STATE_KEY
from torchrl_mbmf.envs.model_based import LearnedDynamicsEnv
from torchrl_mbmf.modules.actors import make_ppo_actor_critic, make_sac_actor_critic
from torchrl_mbmf.modules.dynamics import DeltaDynamicsModel
from torchrl_mbmf.modules.ensemble import EnsembleDeltaDynamicsModel
from torchrl_mbmf.modules.planners import (
    EnsemblePolicyGuidedPlanner,
    MinQValue,
    PolicyGuidedMPCPlanner,
    RandomShootingMPCPlanner,
)
from torchrl_mbmf.trainers.checkpointing import (
    DatasetCheckpointAdapter,
    ReplayCheckpointAdapter,
    TensorStateAdapter,
    VerifiedCheckpoint,
    latest_intact_checkpoint,
)
from torchrl_mbmf.trainers.config import (
    MODEL_BASED,
    PPO_METHODS,
    RESUME_SAFE_SETTINGS,
    ConfigError,
    flatten_config,
    resume_changes,
    validate_train_config,
)
from torchrl_mbmf.trainers.device import resolve_device
from torchrl_mbmf.trainers.dynamics import _transition_tensors, fit_dynamics, fit_dynamics_kwargs
from torchrl_mbmf.trainers.ensemble_fit import calibrate_disagreement_threshold, fit_ensemble
from torchrl_mbmf.trainers.export import save_policy
from torchrl_mbmf.trainers.fit_records import heldout_open_loop_errors, save_fit_snapshot
from torchrl_mbmf.trainers.guards import check_finite
from torchrl_mbmf.trainers.ppo import FusedPPOUpdate, ppo_update
from torchrl_mbmf.trainers.resume_logs import append_resume_log, cut_csv_logs
from torchrl_mbmf.trainers.sac import FusedSACUpdate, ReplaySampler, sac_update_step

logger = logging.getLogger(__name__)


def _fingerprint(cfg: Any) -> dict[str, Any]:
    """Config entries a checkpoint must agree on to be resumed."""
    algo = "ppo" if cfg.method in PPO_METHODS else "sac"
    fingerprint = {
        "method": cfg.method,
        "env.id": cfg.env.id,
        "env.num_envs": int(cfg.env.num_envs),
        "reward": OmegaConf.to_container(cfg.reward, resolve=True),
        "seed": int(cfg.seed),
        f"{algo}.hidden_sizes": list(cfg[algo].hidden_sizes),
        f"{algo}.frames_per_batch": int(cfg[algo].frames_per_batch),
    }
    if cfg.method in MODEL_BASED:
        fingerprint["world_model.hidden_sizes"] = list(cfg.world_model.hidden_sizes)
        fingerprint["world_model.random_steps"] = int(cfg.world_model.random_steps)
        for key in ("ensemble_size", "probabilistic", "multi_step", "multi_step_weight"):
            if key in cfg.world_model:
                fingerprint[f"world_model.{key}"] = cfg.world_model[key]
        fingerprint["planner"] = OmegaConf.to_container(cfg.planner, resolve=True)
    if cfg.method in ("mpc", "ppo_mpc"):
        fingerprint["planning_updates"] = int(cfg.planning_updates)
    return fingerprint


def _machine() -> dict[str, Any]:
    """Software and hardware a run ran on (written beside its config)."""
    import platform

    import torchrl

    return {
        "python": platform.python_version(),
        "torch": torch.__version__,
        "torchrl": torchrl.__version__,
        "cpu_count": os.cpu_count(),
        "machine": platform.machine(),
        "torch_threads": torch.get_num_threads(),
    }


def _git_commit() -> str:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            timeout=5,
            cwd=Path(__file__).resolve().parent,
        )
        return out.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def seed_everything(seed: int) -> None:
    """Seeds Python, NumPy and torch.

    Args:
        seed: the seed.

    Examples:
        >>> from torchrl_mbmf.trainers.loop import seed_everything
        >>> seed_everything(0)
    """
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


class Trainer:
    """Runs one training method end to end from a composed ``train`` config.

    Methods (thesis sections 5.1, 5.4):

    - ``ppo``: stock :class:`~torchrl.objectives.ClipPPOLoss` with GAE on real data.
    - ``ppo_mpc``: fit the world model on random-policy data (those real steps count), then the
      :class:`~torchrl_mbmf.modules.PolicyGuidedMPCPlanner` collects ``ppo.frames_per_batch``
      real steps per PPO update; all real transitions join the dataset, the model is refit on
      it every ``world_model.refit_every`` updates; after ``planning_updates`` updates the same
      actor and critic continue as pure PPO on the real env (warm start).
    - ``mpc``: as ``ppo_mpc`` with the :class:`~torchrl_mbmf.modules.RandomShootingMPCPlanner`
      (PPO trains on its transitions, as in the thesis).
    - ``sac`` / ``sac_mpc``: stock :class:`~torchrl.objectives.SACLoss` with a replay buffer;
      ``sac_mpc`` acts through the policy-guided planner with the SAC actor, starts its replay
      buffer with the random-data steps and refits the model every
      ``sac.refit_every_steps`` real steps.

    Every real env step counts toward ``total_steps``, the random-data steps included.
    Checkpoints (``torchrl.checkpoint``, atomic, rotated) are written every
    ``checkpoint.every_steps`` real steps, between two collectors: the collector is closed and
    the next one starts from envs reseeded with ``seed + real_steps``, so the episode in
    progress is truncated there (GAE bootstraps it like any batch end). This happens in an
    uninterrupted run exactly as in a resumed one, so a run killed and resumed from its latest
    checkpoint ends with the same weights as one that never stopped (on CPU, same thread count).
    A new ``Trainer`` on the same ``run_dir`` resumes from the latest checkpoint; it refuses
    any changed setting outside :data:`~torchrl_mbmf.trainers.config.RESUME_SAFE_SETTINGS`
    (naming each, with both values), records the allowed ones in ``resume_log.json`` and cuts
    the CSV logs back to the checkpoint (removes them when there is none), so the logs of a
    killed-and-resumed run equal an uninterrupted run's.

    Args:
        cfg: the composed config (see ``configs/train.yaml``).
        run_dir: the run folder (logs, config, checkpoints, summary).

    Examples:
        >>> import tempfile
        >>> from hydra import compose, initialize_config_dir
        >>> from pathlib import Path
        >>> from torchrl_mbmf.trainers import Trainer
        >>> configs = str(Path("configs").resolve())
        >>> with initialize_config_dir(configs, version_base="1.3"):  # doctest: +SKIP
        ...     cfg = compose("train", overrides=["method=ppo", "env=pendulum",
        ...                                       "total_steps=400", "ppo.frames_per_batch=200"])
        >>> with tempfile.TemporaryDirectory() as d:  # doctest: +SKIP
        ...     summary = Trainer(cfg, Path(d)).train()
    """

    #: The measured parts of :meth:`time_breakdown` (the rest is ``other_s``).
    TIME_KEYS: tuple[str, ...] = ("env_s", "act_s", "update_s", "refit_s")

    def __init__(self, cfg: Any, run_dir: Path) -> None:
        validate_train_config(cfg)
        self.cfg = cfg
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.method = cfg.method
        self.ppo = cfg.method in PPO_METHODS
        self.model_based = cfg.method in MODEL_BASED
        seed_everything(int(cfg.seed))
        self.times = dict.fromkeys(self.TIME_KEYS, 0.0)
        if cfg.get("threads") is not None:
            torch.set_num_threads(int(cfg.threads))
        # networks, world model, planner and updates; the MuJoCo envs stay on the CPU
        self.device = resolve_device(cfg.get("device", "cpu"))
        self.env = self._make_env(int(cfg.seed))
        self.eval_env = self._make_env(int(cfg.seed) + 1000, num_envs=1)
        self.progress: dict[str, Any] = {
            "real_steps": 0,
            "random_steps": 0,
            "updates": 0,
            "phase": "random" if self.model_based else "model_free",
            "episodes": 0,
            "last_returns": [],
            "next_eval": 0,
            "next_checkpoint": int(cfg.checkpoint.every_steps),
            "next_refit": 0,
            "switch_step": None,
            "fingerprint": _fingerprint(cfg),
            # the whole resolved config: a resume refuses any change that affects training
            "config": flatten_config(cfg),
        }
        self._build_agent()
        self._build_model()
        self.logger = get_logger(
            cfg.logger.backend,
            logger_name=str(self.run_dir),
            experiment_name="logs",
        )
        self.checkpoint = self._make_checkpoint()
        self.rotation = CheckpointRotation(
            self.run_dir / "checkpoints", keep_last=int(cfg.checkpoint.keep_last)
        )
        self.resumed = self._maybe_resume()
        (self.run_dir / "config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
        (self.run_dir / "git_commit.txt").write_text(_git_commit() + "\n")
        (self.run_dir / "machine.json").write_text(json.dumps(_machine(), indent=2) + "\n")

    # ------------------------------------------------------------ building
    def _make_env(self, seed: int, num_envs: int | None = None) -> EnvBase:
        cfg = self.cfg
        return make_env(
            cfg.env.id,
            reward=cfg.reward.name,
            reward_kwargs=dict(cfg.reward.kwargs or {}),
            num_envs=int(cfg.env.num_envs if num_envs is None else num_envs),
            seed=seed,
            device=cfg.env.device,
        )

    def _build_agent(self) -> None:
        cfg = self.cfg
        if self.ppo:
            c = cfg.ppo
            self.actor, self.critic = make_ppo_actor_critic(
                self.env,
                hidden_sizes=tuple(c.hidden_sizes),
                distribution=c.distribution,
                init_log_std=float(c.init_log_std),
            )
            self.actor.to(self.device)
            self.critic.to(self.device)
            self.loss = ClipPPOLoss(
                self.actor,
                self.critic,
                clip_epsilon=float(c.clip_epsilon),
                entropy_coeff=float(c.entropy_coeff),
                critic_coeff=float(c.critic_coeff),
                normalize_advantage=True,
            )
            self.gae = GAE(
                gamma=float(c.gamma),
                lmbda=float(c.lmbda),
                value_network=self.critic,
                average_gae=False,
            )
            self.optim = torch.optim.Adam(self.loss.parameters(), lr=float(c.lr))
            self.replay = None
            self.ppo_step = None
            if c.get("update", "stock") != "stock":
                self.ppo_step = FusedPPOUpdate(
                    self.loss,
                    self.gae,
                    self.optim,
                    epochs=int(c.epochs),
                    minibatch_size=int(c.minibatch_size),
                    max_grad_norm=float(c.max_grad_norm),
                    gradients="manual" if c["update"] == "fused" else "autograd",
                )
        else:
            c = cfg.sac
            self.actor, qvalue = make_sac_actor_critic(self.env, hidden_sizes=tuple(c.hidden_sizes))
            self.actor.to(self.device)
            qvalue.to(self.device)
            self.critic = qvalue
            self.loss = SACLoss(
                self.actor,
                qvalue,
                num_qvalue_nets=2,
                alpha_init=float(c.alpha_init),
                action_spec=self.env.full_action_spec_unbatched[self.env.action_key],
            )
            self.loss.to(self.device)
            self.loss.make_value_estimator(gamma=float(c.gamma))
            self.target_updater = SoftUpdate(self.loss, tau=float(c.tau))
            fused = c.get("update", "stock") == "fused"
            # the fused path also uses torch's fused Adam (same update up to float rounding)
            self.optim = torch.optim.Adam(self.loss.parameters(), lr=float(c.lr), fused=fused)
            self.replay = TensorDictReplayBuffer(
                storage=LazyTensorStorage(int(c.replay_size), device=self.device),
                batch_size=int(c.batch_size),
            )
            self.replay_sampler = None
            if fused:
                self.sac_step = FusedSACUpdate(self.loss, self.optim, self.target_updater)
                self.replay_sampler = ReplaySampler(self.replay, self.sac_step.batch_keys)
            else:
                self.sac_step = sac_update_step(self.loss, self.optim, self.target_updater)

    def _build_model(self) -> None:
        self.dataset = None
        self.model = None
        self.planner = None
        if not self.model_based:
            return
        cfg = self.cfg
        state_dim = self.env.full_observation_spec_unbatched[STATE_KEY].shape[-1]
        action_dim = self.env.full_action_spec_unbatched[self.env.action_key].shape[-1]
        wm = cfg.world_model
        members = int(wm.get("ensemble_size", 1) or 1)
        if members > 1:
            self.model = EnsembleDeltaDynamicsModel(
                state_dim,
                action_dim,
                num_members=members,
                hidden_sizes=tuple(wm.hidden_sizes),
                probabilistic=bool(wm.get("probabilistic", False)),
            ).to(self.device)
            model_env = EnsembleLearnedDynamicsEnv(self.model, self.env)
        else:
            self.model = DeltaDynamicsModel(
                state_dim, action_dim, hidden_sizes=tuple(wm.hidden_sizes)
            ).to(self.device)
            model_env = LearnedDynamicsEnv(self.model, self.env)
        self.model_optim = torch.optim.Adam(self.model.parameters(), lr=float(wm.lr))
        self.dataset = TransitionDataset({**env_metadata(self.env), "seed": int(cfg.seed)})
        p = cfg.planner
        kwargs = {
            "num_candidates": int(p.num_candidates),
            "horizon": int(p.horizon),
            "discount": float(p.discount),
        }
        if p.get("terminal_value", False):
            # PPO: the critic V(s_h) (the loss trains this module's own parameters); SAC: the
            # min over the loss' Q-networks at the actor's action.
            kwargs["value_module"] = (
                self.critic
                if self.method in PPO_METHODS
                else MinQValue(self.actor, self.critic, self.loss.qvalue_network_params)
            )
        if self.method == "mpc":
            self.planner = RandomShootingMPCPlanner(model_env, actor=self.actor, **kwargs)
        else:
            if p.get("refinement"):
                kwargs.update(
                    refinement=str(p.refinement),
                    iterations=int(p.iterations),
                    num_elites=int(p.num_elites),
                    policy_fraction=float(p.policy_fraction),
                    temperature=float(p.temperature),
                    min_std=float(p.min_std),
                )
            if members > 1:
                # Candidate i rolls in member i mod K; with world_model.adaptive_horizon the
                # threshold is calibrated at every refit (None until the first one).
                self.planner = EnsemblePolicyGuidedPlanner(model_env, self.actor, **kwargs)
            else:
                self.planner = PolicyGuidedMPCPlanner(model_env, self.actor, **kwargs)

    def _make_checkpoint(self) -> VerifiedCheckpoint:
        # Every component is restored without pickle, and only after the whole checkpoint
        # passed its integrity record (see torchrl_mbmf.trainers.checkpointing).
        checkpoint = VerifiedCheckpoint()
        checkpoint.register("progress", self.progress, adapter=JSONCheckpointAdapter())
        state = TensorStateAdapter()
        components: dict[str, Any] = {
            "loss": self.loss,
            "optim": self.optim,
            "rng": GlobalRNGState(),
        }
        if self.model is not None:
            components["world_model"] = self.model
            components["model_optim"] = self.model_optim
        if self.logger is not None and hasattr(self.logger, "state_dict"):
            components["logger"] = self.logger
        for name, component in components.items():
            checkpoint.register(name, component, adapter=state)
        if self.dataset is not None:
            checkpoint.register("dataset", self.dataset, adapter=DatasetCheckpointAdapter())
        if self.replay is not None:
            adapter = ReplayCheckpointAdapter(keys=self.loss.in_keys)
            checkpoint.register("replay", self.replay, adapter=adapter)
        return checkpoint

    def _maybe_resume(self) -> bool:
        # the newest checkpoint that passes its integrity record (older one on damage)
        latest = latest_intact_checkpoint(self.rotation)
        if latest is None:
            # A run killed before its first checkpoint starts again: its rows go.
            removed = self._cut_logs({})
            if removed:
                append_resume_log(self.run_dir, {"event": "restart", "removed_rows": removed})
            return False
        expected = dict(self.progress["fingerprint"])
        config = self.progress["config"]
        # Compare the config first (the progress entry alone), then restore everything.
        self.checkpoint.load(latest, components=["progress"])
        saved = self.progress.get("config")
        allowed: dict[str, tuple[Any, Any]] = {}
        if saved is None:  # written before whole configs were saved: the fingerprint only
            logger.warning("%s predates saved configs: only its fingerprint is compared", latest)
            refused = {
                key: (self.progress["fingerprint"].get(key), value)
                for key, value in expected.items()
                if self.progress["fingerprint"].get(key) != value
            }
        else:
            refused, allowed = resume_changes(saved, config)
        if refused:
            lines = "\n".join(
                f"  was written with {key}={old!r}, this run has {key}={new!r}"
                for key, (old, new) in refused.items()
            )
            raise ConfigError(
                f"checkpoint {latest} was written with other settings that change training:\n"
                f"{lines}\nuse another run_dir or the original config (settings a resume may "
                f"change: {list(RESUME_SAFE_SETTINGS)})"
            )
        self.checkpoint.load(latest)
        self.progress["config"] = config
        self.progress["fingerprint"] = expected
        threshold = self.progress.get("disagreement_threshold")
        if threshold is not None and self.planner is not None:
            self.planner.disagreement_threshold = float(threshold)
        cut = self._cut_logs(self.logger.experiment.scalars if self._csv_logs() else {})
        append_resume_log(
            self.run_dir,
            {
                "event": "resume",
                "checkpoint": latest.name,
                "real_steps": self.progress["real_steps"],
                "allowed_changes": {
                    key: {"checkpoint": old, "now": new} for key, (old, new) in allowed.items()
                },
                "removed_rows": cut,
            },
        )
        logger.info("resumed from %s at %d real steps", latest, self.progress["real_steps"])
        return True

    def _csv_logs(self) -> bool:
        return isinstance(self.logger, CSVLogger)

    def _cut_logs(self, rows: dict[str, Any]) -> dict[str, int]:
        """Cuts the CSV series back to ``rows`` (see :func:`cut_csv_logs`)."""
        if not self._csv_logs():
            if self.logger is not None and self.rotation.latest() is not None:
                logger.warning("logs of backend %s are not cut on resume", self.cfg.logger.backend)
            return {}
        return cut_csv_logs(Path(self.logger.experiment.log_dir) / "scalars", rows)

    # ------------------------------------------------------------- logging
    def log(self, metrics: dict[str, float], step: int | None = None) -> None:
        """Logs scalars at the current real-step count.

        Raises:
            TrainingDivergedError: if a value is NaN or infinite (nothing of the call is logged).
        """
        step = self.progress["real_steps"] if step is None else step
        values = {name: float(value) for name, value in metrics.items()}
        check_finite(values, step)
        if self.logger is None:
            return
        for name, value in values.items():
            self.logger.log_scalar(name, value, step=step)

    def _log_episodes(self, batch: TensorDictBase) -> None:
        done = batch.get(("next", "done"))[..., 0]
        if not done.any():
            return
        returns = batch.get(("next", "episode_reward"))[..., 0][done]
        last = deque(self.progress["last_returns"], maxlen=10)
        for r in returns.tolist():
            self.progress["episodes"] += 1
            last.append(r)
            self.log({"train/episode_return": r})
        self.progress["last_returns"] = list(last)
        arr = np.asarray(last)
        self.log(
            {
                "train/return_last10_mean": arr.mean(),
                "train/return_last10_min": arr.min(),
                "train/return_last10_max": arr.max(),
                "train/episodes": self.progress["episodes"],
                "train/real_steps_without_random": self.progress["real_steps"]
                - self.progress["random_steps"],
            }
        )

    def evaluate(self) -> float:
        """Mean return of the policy alone, deterministic, over ``eval_episodes`` episodes."""
        returns = []
        self.eval_env.set_seed(int(self.cfg.seed) + 1000 + self.progress["real_steps"])
        lean = self.cfg.get("collector", "lean") == "lean" and LeanCollector.supports(self.eval_env)
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            for _ in range(int(self.cfg.eval_episodes)):
                if lean:  # the same episode as env.rollout (tested), without its overhead
                    td = LeanCollector(
                        self.eval_env,
                        self.actor,
                        frames_per_batch=1,
                        exploration_type=ExplorationType.DETERMINISTIC,
                        policy_device=self.device,
                    ).episode()
                elif self.device.type != "cpu":
                    td = self.eval_env.rollout(100_000, self._cpu_actor())
                else:
                    td = self.eval_env.rollout(100_000, self.actor)
                returns.append(float(td.get(("next", "reward")).sum()))
        mean = float(np.mean(returns))
        check_finite({"eval/return": mean}, self.progress["real_steps"])
        return mean

    # ---------------------------------------------------------- model part
    def refit_model(self) -> None:
        """Refits the world model on every real transition so far."""
        wm = self.cfg.world_model
        seed = int(self.cfg.seed) + self.progress["updates"]
        # The model being replaced, on the policy's transitions it never trained on (own
        # generator: no training number changes).
        since = self.progress.get("last_fit_transitions")
        heldout = {}
        if since is not None and isinstance(self.model, DeltaDynamicsModel):
            heldout = heldout_open_loop_errors(
                self.model, self.dataset, since=int(since), seed=int(self.cfg.seed)
            )
        start = time.perf_counter()
        if isinstance(self.model, EnsembleDeltaDynamicsModel):
            history = fit_ensemble(
                self.model,
                self.dataset,
                batch_size=int(wm.batch_size),
                max_epochs=int(wm.max_epochs),
                val_fraction=float(wm.val_fraction),
                patience=int(wm.patience),
                seed=seed,
                optimizer=self.model_optim,
            )
        else:
            history = fit_dynamics(
                self.model,
                self.dataset,
                **fit_dynamics_kwargs(wm),
                seed=seed,
                optimizer=self.model_optim,
            )
        scalars = {
            "model/train_loss": history.train_loss[-1],
            "model/val_loss": history.best_val_loss,
            "model/epochs": history.epochs,
            "model/transitions": len(self.dataset),
        }
        if getattr(history, "multi_step", 1) > 1:
            scalars["model/train_multi_step_loss"] = history.train_multi_step_loss[-1]
            scalars["model/val_multi_step_loss"] = history.best_val_multi_step_loss
        if isinstance(self.model, EnsembleDeltaDynamicsModel) and wm.get("adaptive_horizon"):
            # Calibrated on the fit's held-out split, which no member trained on.
            state, action, next_state, _ = _transition_tensors(self.dataset)
            idx = history.val_indices
            calibration = calibrate_disagreement_threshold(
                self.model,
                state[idx],
                action[idx],
                next_state[idx],
                quantile=float(wm.disagreement_quantile),
            )
            self.progress["disagreement_threshold"] = float(calibration.threshold)
            self.planner.disagreement_threshold = float(calibration.threshold)
            scalars["model/disagreement_threshold"] = float(calibration.threshold)
        self.progress["last_fit_transitions"] = len(self.dataset)
        if wm.get("save_fits", True):
            save_fit_snapshot(self.model, self.run_dir, len(self.dataset))
        scalars["time/model_fit_s"] = time.perf_counter() - start
        self.times["refit_s"] += scalars["time/model_fit_s"]
        self.log({**heldout, **scalars})

    @staticmethod
    def _ensemble_stats(batch: TensorDictBase) -> dict[str, torch.Tensor]:
        """Effective horizon and disagreement of an ensemble planner's batch (else none)."""
        out = {}
        for name in ("effective_horizon", "disagreement"):
            if ("planner", name) in batch.keys(True):
                out[f"planner/{name}"] = batch["planner", name].float().mean()
        return out

    def _collector(self, policy: Any, frames: int, total: int) -> Any:
        """The lean collector where the env supports it (``collector=lean``), else the stock one."""
        if self.cfg.get("collector", "lean") == "lean" and LeanCollector.supports(self.env):
            return LeanCollector(
                self.env,
                policy,
                frames_per_batch=frames,
                total_frames=total,
                policy_device=self.device,
            )
        devices = {}
        if self.device.type != "cpu":
            devices = {"policy_device": self.device, "env_device": "cpu", "storing_device": "cpu"}
        return Collector(
            self.env,
            policy,
            frames_per_batch=frames,
            total_frames=total,
            auto_register_policy_transforms=False,
            **devices,
        )

    def _close_collector(self, collector: Any) -> None:
        times = getattr(collector, "times", None)
        if times is not None:
            self.times["env_s"] += times.env_s
            self.times["act_s"] += times.act_s
        collector.shutdown()

    def collect_random(self, bar: tqdm) -> None:
        """Random-policy real steps that fit the first model (counted in the budget)."""
        steps = int(self.cfg.world_model.random_steps)
        n = max(1, self.env.batch_size.numel())
        frames = min(1000 * n, -(-steps // n) * n)
        collector = self._collector(
            RandomPolicy(self.env.full_action_spec), frames, -(-steps // frames) * frames
        )
        for batch in collector:
            self._count(batch, bar, random=True)
            self.dataset.extend(batch)
            if self.replay is not None:
                self.replay.extend(self._replay_view(batch))
        self._close_collector(collector)
        self.refit_model()
        self.progress["phase"] = "planning"

    # -------------------------------------------------------------- updates
    def ppo_update(self, batch: TensorDictBase) -> None:
        """Thesis PPO: GAE once per batch, ``epochs`` passes of ``minibatch_size`` minibatches."""
        c = self.cfg.ppo
        if self.device.type != "cpu":
            batch = batch.to(self.device)
        if self.ppo_step is not None:
            stats = self.ppo_step(batch)
        else:
            stats = ppo_update(
                self.loss,
                self.gae,
                self.optim,
                batch,
                epochs=int(c.epochs),
                minibatch_size=int(c.minibatch_size),
                max_grad_norm=float(c.max_grad_norm),
            )
        self.progress["updates"] += 1
        scale = self.actor.module[0].module[-1].state_independent_scale
        self.log({f"loss/{k}": v for k, v in stats.items()})
        self.log(
            {
                "train/policy_log_std": float(scale.detach().mean()),
                "train/updates": self.progress["updates"],
            }
        )

    def _cpu_actor(self) -> Any:
        """A CPU copy of the actor (the stock env rollout runs the policy where the env is)."""
        import copy

        return copy.deepcopy(self.actor).to("cpu")

    def _replay_view(self, batch: TensorDictBase) -> TensorDictBase:
        """The entries SACLoss reads, flattened (planner extras and log-probs are dropped)."""
        return batch.reshape(-1).select(*self.loss.in_keys, strict=False)

    def sac_update(self, batch: TensorDictBase) -> None:
        """``utd_ratio`` SAC updates per collected frame past the initial random frames.

        As in Stable-Baselines3 (``learning_starts``) and torchrl's SAC recipe: the frames up
        to ``sac.init_random_frames`` take no update, every later frame ``utd_ratio`` updates
        (done after each collected batch).
        """
        c = self.cfg.sac
        self.replay.extend(self._replay_view(batch))
        steps = self.progress["real_steps"]
        past = steps - max(int(c.init_random_frames), steps - batch.numel())
        updates = round(past * float(c.utd_ratio))
        if updates <= 0:
            return
        stats: dict[str, list[torch.Tensor]] = {}
        for _ in range(updates):
            if self.replay_sampler is not None:
                out = self.sac_step.update(*self.replay_sampler())
            else:
                out = self.sac_step(self.replay.sample())
            for k, v in out.items():
                stats.setdefault(k, []).append(torch.as_tensor(v).detach())
        self.progress["updates"] += 1
        self.log({f"loss/{k}": float(torch.stack(v).float().mean()) for k, v in stats.items()})
        scale = batch.get("scale", None)
        if scale is not None:
            self.log({"train/policy_log_std": float(scale.log().mean())})

    # ----------------------------------------------------------------- loop
    def _count(self, batch: TensorDictBase, bar: tqdm, random: bool = False) -> None:
        n = batch.numel()
        self.progress["real_steps"] += n
        if random:
            self.progress["random_steps"] += n
        bar.update(n)
        self._log_episodes(batch)

    def _policy(self) -> Any:
        if self.progress["phase"] == "planning":
            return self.planner
        if self.method == "sac" and self.progress["real_steps"] < int(
            self.cfg.sac.init_random_frames
        ):
            return RandomPolicy(self.env.full_action_spec)
        return self.actor

    def _planning_done(self) -> bool:
        if self.method in ("mpc", "ppo_mpc"):
            return self.progress["updates"] >= int(self.cfg.planning_updates)
        return False

    def train(self) -> dict[str, Any]:
        """Runs until ``total_steps`` real steps; returns (and writes) a summary."""
        cfg = self.cfg
        total = int(cfg.total_steps)
        bar = tqdm(
            total=total,
            initial=self.progress["real_steps"],
            desc=cfg.method,
            unit="step",
            disable=not cfg.progress,
        )
        start = time.perf_counter()
        start_steps = self.progress["real_steps"]
        if self.progress["phase"] == "random":
            self.collect_random(bar)
            self.progress["next_refit"] = self.progress["real_steps"] + int(
                cfg.sac.refit_every_steps
            )
        frames = int((cfg.ppo if self.ppo else cfg.sac).frames_per_batch)
        while self.progress["real_steps"] < total:
            if self._planning_done() and self.progress["phase"] == "planning":
                self.progress["phase"] = "model_free"
                self.progress["switch_step"] = self.progress["real_steps"]
                self.log({"train/switch_to_model_free": 1.0})
                logger.info("warm start: pure PPO from %d real steps", self.progress["real_steps"])
            policy = self._policy()
            # Every collector starts from freshly seeded envs, so a resumed run continues
            # exactly like an uninterrupted one (checkpoints happen between collectors).
            self.env.set_seed(int(cfg.seed) + self.progress["real_steps"])
            collector = self._collector(policy, frames, -1)
            lean = isinstance(collector, LeanCollector)
            phase = self.progress["phase"]
            t_wait = time.perf_counter()
            for batch in collector:
                t_collect = time.perf_counter()
                if not lean:  # the stock collector's env and policy time, not separable
                    self.times["env_s"] += t_collect - t_wait
                self._count(batch, bar)
                if phase == "planning":
                    self.dataset.extend(batch)
                    if ("planner", "best_return") in batch.keys(True):
                        self.log(
                            {
                                "planner/best_return": batch["planner", "best_return"].mean(),
                                "planner/mean_return": batch["planner", "mean_return"].mean(),
                                **self._ensemble_stats(batch),
                            }
                        )
                t_update = time.perf_counter()
                if self.ppo:
                    self.ppo_update(batch)
                    # no refit once the planning phase is over: nothing plans with it again
                    refit = (
                        phase == "planning"
                        and self.progress["updates"] % int(cfg.world_model.refit_every) == 0
                        and not self._planning_done()
                    )
                else:
                    self.sac_update(batch)
                    refit = (
                        phase == "planning"
                        and self.progress["real_steps"] >= self.progress["next_refit"]
                    )
                    if refit:
                        self.progress["next_refit"] += int(cfg.sac.refit_every_steps)
                self.times["update_s"] += time.perf_counter() - t_update
                if refit:
                    self.refit_model()
                self.log(
                    {
                        "time/update_s": time.perf_counter() - t_collect,
                        "time/steps_per_s": (self.progress["real_steps"] - start_steps)
                        / max(1e-9, time.perf_counter() - start),
                    }
                )
                if self.progress["real_steps"] >= self.progress["next_eval"]:
                    if int(cfg.eval_episodes) > 0:
                        self.log({"eval/return": self.evaluate()})
                    self.progress["next_eval"] += int(cfg.eval_every)
                t_wait = time.perf_counter()
                checkpoint_due = self.progress["real_steps"] >= self.progress["next_checkpoint"]
                if checkpoint_due or self.progress["real_steps"] >= total:
                    break
                if self._planning_done() and phase == "planning":
                    break
                if self._policy() is not policy:
                    break
            self._close_collector(collector)
            if self.progress["real_steps"] >= self.progress["next_checkpoint"]:
                while self.progress["next_checkpoint"] <= self.progress["real_steps"]:
                    self.progress["next_checkpoint"] += int(cfg.checkpoint.every_steps)
                self.save_checkpoint()
        bar.close()
        self.save_checkpoint()
        summary = {
            "method": cfg.method,
            "env": cfg.env.id,
            "reward": cfg.reward.name,
            "seed": int(cfg.seed),
            "real_steps": self.progress["real_steps"],
            "random_steps": self.progress["random_steps"],
            "updates": self.progress["updates"],
            "episodes": self.progress["episodes"],
            "switch_step": self.progress["switch_step"],
            "last10_mean_return": float(np.mean(self.progress["last_returns"]))
            if self.progress["last_returns"]
            else None,
            "final_eval_return": self.evaluate() if int(cfg.eval_episodes) > 0 else None,
            "params_sha256": self.parameters_digest(),
            "seconds": time.perf_counter() - start,
            "resumed": self.resumed,
        }
        summary["time_breakdown"] = self.time_breakdown(summary["seconds"])
        (self.run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
        return summary

    def time_breakdown(self, seconds: float) -> dict[str, float]:
        """Where this process' training time went, in seconds.

        ``env_s``: real env steps with their transforms (with the stock collector, the policy's
        time too); ``act_s``: the actor or planner; ``update_s``: PPO/SAC updates; ``refit_s``:
        world-model refits; ``other_s``: the rest (logging, evaluation, checkpoints, datasets).

        Args:
            seconds: the wall time the breakdown splits.

        Examples:
            >>> from torchrl_mbmf.trainers import Trainer
            >>> sorted(Trainer.TIME_KEYS)
            ['act_s', 'env_s', 'refit_s', 'update_s']
        """
        out = {key: float(self.times[key]) for key in self.TIME_KEYS}
        out["other_s"] = max(0.0, float(seconds) - sum(out.values()))
        return out

    def parameters_digest(self) -> str:
        """SHA-256 of every trained tensor (policy, critics, world model): equal runs match."""
        digest = hashlib.sha256()
        modules = [self.loss] + ([self.model] if self.model is not None else [])
        for module in modules:
            for name, tensor in sorted(module.state_dict().items()):
                digest.update(name.encode())
                digest.update(tensor.detach().cpu().contiguous().numpy().tobytes())
        return digest.hexdigest()

    def save_checkpoint(self) -> None:
        """Atomically writes a rotated checkpoint of everything needed to continue."""
        latest = self.rotation.latest()
        step = self.progress["real_steps"]
        if latest is not None and latest.name.endswith(f"{step:012d}"):
            return
        self.rotation.save(self.checkpoint, step=step)
        save_policy(self.actor, self.run_dir, step)
