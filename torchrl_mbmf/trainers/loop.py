"""The training loop of every method: model-free, MBMF planning phase, warm-start fine-tuning."""

from __future__ import annotations

import hashlib
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase
from torchrl.collectors import Collector
from torchrl.envs.utils import RandomPolicy

from torchrl_mbmf.checks import check_finite
from torchrl_mbmf.collectors import LeanCollector
from torchrl_mbmf.collectors.factory import evaluate_policy, make_collector
from torchrl_mbmf.device import resolve_device
from torchrl_mbmf.runs.checkpoint import RunCheckpoint
from torchrl_mbmf.runs.claim import claim_run_folder
from torchrl_mbmf.runs.layout import RunFolder, write_run_record
from torchrl_mbmf.runs.resume import fingerprint
from torchrl_mbmf.runs.signals import StopRequest
from torchrl_mbmf.trainers.agents import Agent, make_agent
from torchrl_mbmf.trainers.build import make_hooks, make_settings_env, seed_everything
from torchrl_mbmf.trainers.config import TrainSettings
from torchrl_mbmf.trainers.planning import WorldModelPart
from torchrl_mbmf.trainers.schedule import Actor, Phase, PhaseSchedule, Progress
from torchrl_mbmf.trainers.settings import TrainConfig
from torchrl_mbmf.world_model.branched_rollouts import BranchedRollouts, policy_as_planner

__all__ = [
    "Trainer",
    "make_run_checkpoint",
    "parameters_digest",
    "run_summary",
    "seed_everything",
    "time_breakdown",
]


class Trainer:
    """Runs one training method end to end from a composed ``train`` config.

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
    TIME_KEYS: tuple[str, ...] = ("env_s", "act_s", "update_s", "refit_s", "rollout_s")

    def __init__(self, cfg: DictConfig, run_dir: Path) -> None:
        # parsed once: nothing reads the raw config after this constructor
        self.config = config = TrainConfig.from_config(cfg)
        self.settings = settings = config.settings
        self.run_dir = Path(run_dir)
        seed_everything(settings.seed)
        self.times = dict.fromkeys(self.TIME_KEYS, 0.0)
        if settings.threads is not None:
            torch.set_num_threads(settings.threads)
        # networks, world model, planner and updates; the MuJoCo envs stay on the CPU
        self.device = resolve_device(settings.device)
        self.env = make_settings_env(config.env, config.reward, settings.seed)
        self.eval_env = make_settings_env(
            config.env, config.reward, settings.seed + 1000, num_envs=1
        )
        # The config groups' components (GroupSettings.build): their constructors check every
        # argument, so a bad value stops the run here, before any work.
        self.agent: Agent = make_agent(settings.family, self.env, config.agent, self.device)
        self.world: WorldModelPart | None = None
        mbpo = settings.method == "sac_mbpo"
        if settings.model_based:
            self.world = config.world_model.build(
                env=self.env,
                agent=self.agent,
                device=self.device,
                planner=policy_as_planner if mbpo else config.planner.build,
                seed=settings.seed,
                guided=settings.method != "mpc",
            )
        self.rollouts: BranchedRollouts | None = None
        if mbpo:  # the model replay and the real/model mix of the SAC batches
            self.rollouts = config.mbpo.build(
                world_model=self.world.model,
                env=self.env,
                actor=self.agent.actor,
                keys=self.agent.loss.in_keys,
                termination_fn=self.world.termination,
                device=self.device,
            )
            self.agent.mix_model_replay(self.rollouts.replay, self.rollouts.real_ratio)
        self.schedule = PhaseSchedule.from_config(config)
        self.progress = Progress(
            phase=self.schedule.first_phase().value,
            next_checkpoint=settings.checkpoint_every,
            fingerprint=fingerprint(cfg),
            # the whole resolved config: a resume refuses any change that affects training
            config=dict(config.record),
        )
        self.frames_per_batch = settings.frames_per_batch
        self.total_steps = settings.total_steps
        # claimed (locked; finished or foreign runs refused) before anything is written to it
        self.lock = claim_run_folder(self.run_dir, config.record, restart=config.restart)
        self.logger = config.logger.build(run_dir=self.run_dir)
        self.hooks, named = make_hooks(config, self.schedule.model_based)
        self.bar, self.timing = named["bar"], named["timing"]
        self.checkpoints = named["checkpoints"]
        self.acting = self.schedule.actor(self.progress)
        self.batch_time = time.perf_counter()
        self.run_checkpoint = make_run_checkpoint(self)
        self.resumed = self.run_checkpoint.resume()
        if self.resumed and self.world is not None:
            self.world.restore(self.progress)
        if "eval_every" in self.run_checkpoint.allowed_changes:
            # a new evaluation schedule applies from the resume point on, as a fresh run's
            progress = self.progress
            progress.next_eval = named["evaluation"].next_eval_at(
                progress.real_steps, progress.random_steps, self.frames_per_batch
            )
        write_run_record(self.run_dir, cfg)

    def count(self, batch: TensorDictBase, random: bool = False) -> None:
        """Counts a collected batch's real steps and runs the ``collected`` hooks."""
        self.batch_time = time.perf_counter()
        self.progress.real_steps += batch.numel()
        if random:
            self.progress.random_steps += batch.numel()
        self.hooks.run("collected", self, batch)

    def collect_random(self) -> None:
        """Random-policy real steps that fit the first model (counted in the budget)."""
        self.acting = Actor.RANDOM
        steps = self.world.random_steps
        n = max(1, self.env.batch_size.numel())
        frames = min(1000 * n, -(-steps // n) * n)
        collector = self.collector(Actor.RANDOM, frames, -(-steps // frames) * frames)
        for batch in collector:
            self.count(batch, random=True)
            self.agent.observe(batch)
        self.close_collector(collector)
        self.refit_model()
        self.schedule.start_planning(self.progress)

    def learn(self, batch: TensorDictBase) -> None:
        """The agent's update on ``batch`` (timed), then the ``updated`` hooks."""
        t_update = time.perf_counter()
        stats = self.agent.update(batch, self.progress.real_steps)
        if stats is not None:
            self.progress.updates += 1
            self.log(stats)
            log_std = self.agent.log_std(batch)
            scalars = {} if log_std is None else {"train/policy_log_std": log_std}
            if self.agent.logs_update_count:
                scalars["train/updates"] = self.progress.updates
            self.log(scalars)
        self.times["update_s"] += time.perf_counter() - t_update
        self.hooks.run("updated", self, batch)

    def collect_round(self) -> None:
        """One collector: from freshly seeded envs until the schedule or a checkpoint ends it."""
        if self.schedule.switch_due(self.progress):
            self.schedule.start_model_free(self.progress)
            self.log({"train/switch_to_model_free": 1.0})
        self.acting = self.schedule.actor(self.progress)
        # freshly seeded envs: a resumed run continues exactly like an uninterrupted one
        self.env.set_seed(self.settings.seed + self.progress.real_steps)
        collector = self.collector(self.acting, self.frames_per_batch, -1)
        lean = isinstance(collector, LeanCollector)
        t_wait = time.perf_counter()
        for batch in collector:
            self.count(batch)
            if not lean:  # the stock collector's env and policy time, not separable
                self.times["env_s"] += self.batch_time - t_wait
            self.learn(batch)
            t_wait = time.perf_counter()
            if self.round_over():
                break
        self.close_collector(collector)
        self.hooks.run("round_end", self)

    def round_over(self) -> bool:
        """Whether the current collector stops: budget, checkpoint or schedule."""
        progress = self.progress
        if progress.real_steps >= self.total_steps or self.checkpoints.due(progress):
            return True
        return self.schedule.round_over(progress, self.acting)

    def train(self) -> dict[str, Any]:
        """Runs until ``total_steps`` real steps (or a signal's checkpoint); returns a summary."""
        try:
            with StopRequest() as stop:
                return self._train(stop)
        finally:
            self.lock.release()

    def _train(self, stop: StopRequest) -> dict[str, Any]:
        self.bar.open(self.progress.real_steps)
        self.timing.open(self.progress.real_steps)
        start = time.perf_counter()
        if self.schedule.phase(self.progress) is Phase.RANDOM:
            self.collect_random()
        while self.progress.real_steps < self.total_steps:
            saved_before = self.progress.next_checkpoint
            self.collect_round()
            stop.keep_installed()
            if stop.requested and self.progress.next_checkpoint != saved_before:
                self.bar.close()
                steps = self.progress.real_steps
                return {"stopped_by": stop.requested, "real_steps": steps, "checkpoint": steps}
        self.bar.close()
        self.save_checkpoint()
        return self.write_summary(time.perf_counter() - start)

    # ------------------------------------------------------------- services
    def refit_model(self) -> None:
        """Refits the world model on every real transition so far (and logs the fit)."""
        seed = self.settings.seed + self.progress.updates
        scalars = self.world.refit(seed, self.progress, self.run_dir)
        self.times["refit_s"] += scalars["time/model_fit_s"]
        self.log(scalars)

    def collector(self, acting: Actor, frames: int, total: int) -> Collector | LeanCollector:
        """A collector of ``frames``-frame batches run by the policy ``acting`` names."""
        if acting is Actor.RANDOM:
            policy = RandomPolicy(self.env.full_action_spec)
        else:
            policy = self.world.planner if acting is Actor.PLANNER else self.agent.actor
        kind = self.settings.collector
        return make_collector(self.env, policy, frames, total, self.device, kind)

    def close_collector(self, collector: Collector | LeanCollector) -> None:
        """Adds a lean collector's env and policy time, then shuts the collector down."""
        times = getattr(collector, "times", None)
        if times is not None:
            self.times["env_s"] += times.env_s
            self.times["act_s"] += times.act_s
        collector.shutdown()

    def log(self, metrics: dict[str, float], step: int | None = None) -> None:
        """Logs scalars at the current real-step count.

        Raises:
            TrainingDivergedError: if a value is NaN or infinite (nothing of the call is logged).
        """
        step = self.progress.real_steps if step is None else step
        values = {name: float(value) for name, value in metrics.items()}
        check_finite(values, step)
        if self.logger is None:
            return
        for name, value in values.items():
            self.logger.log_scalar(name, value, step=step)

    def evaluate(self) -> float:
        """Mean return of the policy alone, deterministic, over ``eval_episodes`` episodes."""
        steps, s = self.progress.real_steps, self.settings
        self.eval_env.set_seed(s.seed + 1000 + steps)
        return evaluate_policy(
            self.eval_env, self.agent.actor, s.eval_episodes, self.device, s.collector, steps
        )

    def save_checkpoint(self) -> None:
        """Atomically writes a rotated checkpoint of everything needed to continue."""
        self.run_checkpoint.save(self.agent.actor)

    def write_summary(self, seconds: float) -> dict[str, Any]:
        """Writes and returns the run's summary (:func:`run_summary`) after ``seconds``."""
        final = self.evaluate() if self.settings.eval_episodes > 0 else None
        summary = run_summary(
            self.settings, self.progress, final, self.parameters_digest(), seconds, self.resumed
        )
        summary["time_breakdown"] = time_breakdown(self.times, seconds)
        RunFolder(self.run_dir).write_summary(summary)
        return summary

    def parameters_digest(self) -> str:
        """SHA-256 of every trained tensor (policy, critics, world model): equal runs match."""
        modules = [self.agent.loss] + ([] if self.world is None else self.world.trained_modules())
        return parameters_digest(modules)


def make_run_checkpoint(trainer: Trainer) -> RunCheckpoint:
    """The checkpoint of a trainer's run (the parts in :mod:`torchrl_mbmf.runs.checkpoint`).

    Args:
        trainer: the trainer (its parts are built).

    Examples:
        >>> from torchrl_mbmf.trainers.loop import make_run_checkpoint
        >>> callable(make_run_checkpoint)
        True
    """
    agent, world, rollouts = trainer.agent, trainer.world, trainer.rollouts
    tensors = dict(agent.checkpoint_components())
    if world is not None:
        tensors.update(world.checkpoint_components())
    return RunCheckpoint(
        trainer.run_dir,
        trainer.progress,
        tensors,
        trainer.logger,
        keep_last=trainer.settings.keep_last,
        dataset=None if world is None else world.dataset,
        dataset_needed=trainer.schedule.dataset_needed,
        replay=None if agent.replay is None else (agent.replay, agent.loss.in_keys),
        model_replay=rollouts,
        backend=trainer.settings.logger_backend,
    )


def run_summary(
    settings: TrainSettings,
    progress: Progress,
    final_eval_return: float | None,
    params_sha256: str,
    seconds: float,
    resumed: bool,
) -> dict[str, Any]:
    """A finished run's summary: what ran, its counts, its returns, its weights' digest.

    Args:
        settings: the run's settings.
        progress: the loop state at the end.
        final_eval_return: the final evaluation's mean return (``None``: no evaluation).
        params_sha256: :func:`parameters_digest` of the trained modules.
        seconds: the training wall time.
        resumed: whether this process resumed from a checkpoint.

    Examples:
        >>> settings = TrainSettings("ppo", 0, 400, 200, 0, 400, 2, "Pendulum-v1", "default")
        >>> summary = run_summary(settings, Progress(real_steps=400), None, "ab", 1.5, False)
        >>> summary["real_steps"], summary["last10_mean_return"]
        (400, None)
    """
    last = progress.last_returns
    return {
        "method": settings.method,
        "env": settings.env_id,
        "reward": settings.reward,
        "seed": settings.seed,
        **{k: progress[k] for k in ("real_steps", "random_steps", "updates", "episodes")},
        "switch_step": progress.switch_step,
        "last10_mean_return": float(np.mean(last)) if last else None,
        "final_eval_return": final_eval_return,
        "params_sha256": params_sha256,
        "seconds": seconds,
        "resumed": resumed,
    }


def time_breakdown(times: Mapping[str, float], seconds: float) -> dict[str, float]:
    """Where a process' training time went, in seconds.

    ``env_s``: real env steps with their transforms (with the stock collector, the policy's
    time too); ``act_s``: the actor or planner; ``update_s``: PPO/SAC updates; ``refit_s``:
    world-model refits; ``rollout_s``: ``sac_mbpo``'s model rollouts; ``other_s``: the rest
    (logging, evaluation, checkpoints, datasets).

    Args:
        times: the measured seconds of :data:`Trainer.TIME_KEYS`.
        seconds: the wall time the breakdown splits.

    Examples:
        >>> times = {"env_s": 1.0, "act_s": 2.0, "update_s": 3.0, "refit_s": 0.0, "rollout_s": 1}
        >>> time_breakdown(times, 10)["other_s"]
        3.0
    """
    out = {key: float(times.get(key, 0.0)) for key in Trainer.TIME_KEYS}
    out["other_s"] = max(0.0, float(seconds) - sum(out.values()))
    return out


def parameters_digest(modules: Sequence[torch.nn.Module]) -> str:
    """SHA-256 of every tensor of ``modules``' state dicts, in name order.

    Args:
        modules: the modules (their ``state_dict``).

    Examples:
        >>> a, b = torch.nn.Linear(2, 1), torch.nn.Linear(2, 1)
        >>> _ = b.load_state_dict(a.state_dict())
        >>> parameters_digest([a]) == parameters_digest([b])
        True
    """
    digest = hashlib.sha256()
    for module in modules:
        for name, tensor in sorted(module.state_dict().items()):
            digest.update(name.encode())
            digest.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()
