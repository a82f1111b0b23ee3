"""MBPO's branched model rollouts: short imagined branches from real states into a model replay.

Model-based policy optimisation (Janner et al. 2019, "When to trust your model") trains an
off-policy agent on a mix of real transitions and transitions imagined by a learned ensemble:
every ``rollout_every`` real steps it samples ``rollout_batch_size`` states the real env
visited, rolls each one ``rollout_horizon`` steps in the ensemble with the current (stochastic)
policy, each step in a member drawn at random, stops a branch at its first predicted
termination, and keeps the imagined transitions in a model replay of bounded retention.
:class:`BranchedRollouts` does that with the package's learned env
(:class:`RandomMemberEnv`, a :class:`~torchrl_mbmf.envs.EnsembleLearnedDynamicsEnv` whose
every step uses a random member) and its ``rollout``; the SAC agent then draws its batches
from both replays through :class:`~torchrl_mbmf.data.mixed_replay.MixedReplaySampler`.
Design: ``docs/design/mbpo.md``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_mbmf.checks import ConfigError, Setting, check_arguments, settings
from torchrl_mbmf.data.transitions import TransitionDataset
from torchrl_mbmf.envs.ensemble_env import EnsembleLearnedDynamicsEnv
from torchrl_mbmf.envs.model_based import LearnedDynamicsEnv
from torchrl_mbmf.envs.terminations import TerminationFn
from torchrl_mbmf.modules.dynamics import DeltaDynamicsModel

__all__ = [
    "BranchedRollouts",
    "RandomMemberEnv",
    "RolloutRounds",
    "check_mbpo_config",
    "policy_as_planner",
]


def check_mbpo_config(cfg: Mapping[str, Any]) -> None:
    """Checks a ``sac_mbpo`` train config across groups.

    The ``mbpo`` keys' own ranges are checked by :class:`BranchedRollouts`.

    Args:
        cfg: the composed train config (``sac``, ``mbpo``, ``planner`` and ``world_model``).

    Raises:
        ConfigError: naming the key: no ``mbpo`` group, a rollout or refit period that is no
            multiple of ``sac.frames_per_batch``, or a planner or world-model option that has
            no effect because nothing plans.

    Examples:
        >>> cfg = {"sac": {"frames_per_batch": 50}, "mbpo": {"rollout_every": 75},
        ...        "planner": {}, "world_model": {}}
        >>> try:
        ...     check_mbpo_config(cfg)
        ... except ValueError as err:
        ...     print(str(err).split(" (")[0])
        mbpo.rollout_every=75 must be a multiple of sac.frames_per_batch=50
    """
    if "mbpo" not in cfg:
        raise ConfigError("method=sac_mbpo needs the mbpo group (configs/mbpo/default.yaml)")
    frames = cfg["sac"]["frames_per_batch"]
    for key in ("rollout_every", "refit_every"):
        every = cfg["mbpo"].get(key)
        ints = all(type(v) is int and v > 0 for v in (frames, every))
        if ints and every % frames:
            raise ConfigError(
                f"mbpo.{key}={every} must be a multiple of sac.frames_per_batch={frames} "
                "(rollouts and refits happen between collected batches)"
            )
    if cfg["planner"].get("terminal_value", False) is True:
        raise ConfigError(
            "planner.terminal_value=true has no effect with method=sac_mbpo (nothing plans: "
            "the actor acts); set planner.terminal_value=false"
        )
    if cfg["world_model"].get("adaptive_horizon", False) is True:
        raise ConfigError(
            "world_model.adaptive_horizon=true has no effect with method=sac_mbpo (its "
            "rollouts have the fixed length mbpo.rollout_horizon); set it to false"
        )


class RandomMemberEnv(EnsembleLearnedDynamicsEnv):
    """The ensemble's learned env with each element's member drawn at random at every step.

    MBPO's model: a step of batch element ``b`` is the prediction of a member drawn uniformly
    (``torch.randint`` on the global generator, so a seeded or resumed run draws the same
    ones), where :class:`~torchrl_mbmf.envs.EnsembleLearnedDynamicsEnv` cycles members by
    position; a probabilistic ensemble (``world_model.probabilistic``) samples that member's
    Gaussian (its mean plus its standard deviation times ``torch.randn``, in scaled units), as
    MBPO does, where the other learned envs step the mean. Everything else (specs,
    terminations, observation, disagreement) is the ensemble env's.

    Args:
        world_model: the ensemble (``ensemble_size >= 2``).
        env: the real env whose specs are copied.

    Keyword Args:
        **kwargs: the keywords of :class:`~torchrl_mbmf.envs.LearnedDynamicsEnv`
            (``termination_fn``, ``device``, ...).

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.envs import make_env
        >>> from torchrl_mbmf.modules import EnsembleDeltaDynamicsModel
        >>> real = make_env("Pendulum-v1", seed=0)
        >>> model = EnsembleDeltaDynamicsModel(3, 1, num_members=3, hidden_sizes=(8,))
        >>> env = RandomMemberEnv(model, real)
        >>> members = env._members_of(torch.Size([4, 6]))
        >>> members.shape, bool(((members >= 0) & (members < 3)).all())
        (torch.Size([4, 6]), True)
    """

    def __init__(self, world_model: DeltaDynamicsModel, env: EnvBase, **kwargs: object) -> None:
        super().__init__(world_model, env, **kwargs)

    def _members_of(self, batch_size: torch.Size) -> torch.Tensor:
        k = self.dynamics.num_members
        return torch.randint(0, k, tuple(batch_size), device=self.device)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        state, action = tensordict.get(self.state_key), tensordict.get(self.action_key)
        members = self._members_of(tensordict.batch_size)
        model = self.dynamics
        mean, log_var = model.predict_scaled_members(state, action)  # [K, *B, d + 1]
        index = members.unsqueeze(0).unsqueeze(-1).expand(1, *mean.shape[1:])
        out = mean.gather(0, index).squeeze(0)
        if log_var is not None:
            std = (0.5 * log_var.gather(0, index).squeeze(0)).exp()
            out = out + std * torch.randn_like(out)
        next_state, reward = model.unscale(state, out)
        terminated = self.terminated(next_state).unsqueeze(-1)
        td = self._fill(next_state, tensordict.batch_size, terminated)
        td.set(self.reward_key, reward)
        td.set(self.disagreement_key, model.disagreement_of_scaled(mean).unsqueeze(-1))
        return td


class RolloutRounds:
    """What re-runs exactly each rollout round whose rows are still in the model replay.

    Before a round (:meth:`begin`): the global torch random state, the torch thread count, the
    number of real transitions, the model replay's writer state and the parameters of the actor,
    the model and a learned termination head (each distinct set kept once); after it
    (:meth:`end`): the rows it added. A round whose rows are all overwritten is dropped. A
    checkpoint holds it as tensor state (``model_rounds``); recording draws no random number.
    :mod:`torchrl_mbmf.runs.buffer_replay` rebuilds the model replay from it.

    Examples:
        >>> import torch
        >>> rounds = RolloutRounds()
        >>> net = torch.nn.Linear(2, 1)
        >>> for cursor in (0, 40):
        ...     rounds.begin(100, {"_cursor": cursor, "_write_count": cursor}, [net, net, None])
        ...     rounds.end(40, capacity=50)
        >>> [r["cursor"] for r in rounds.rounds], len(rounds.params)  # both partly kept
        ([0, 40], 1)
    """

    def __init__(self) -> None:
        self.rounds: list[dict[str, Any]] = []
        self.params: list[dict[str, torch.Tensor]] = []

    def _ref(self, module: object) -> int:
        if not isinstance(module, torch.nn.Module):
            return -1
        state = {k: v.detach().clone() for k, v in module.state_dict().items()}
        for i, known in enumerate(self.params):
            if known.keys() == state.keys() and all(torch.equal(known[k], state[k]) for k in state):
                return i
        self.params.append(state)
        return len(self.params) - 1

    def begin(self, real: int, writer: Mapping[str, Any], modules: Sequence[object]) -> None:
        """Records the state a round starts from.

        Args:
            real: the number of real transitions its start states are drawn from.
            writer: the model replay's writer state (``_cursor``, ``_write_count``).
            modules: the actor, the model and the termination function (a module or not).
        """
        actor, model, termination = (self._ref(m) for m in modules)
        self.rounds.append(
            {
                "rng": torch.get_rng_state(),
                "threads": torch.get_num_threads(),
                "real": int(real),
                "cursor": int(writer["_cursor"]),
                "write_count": int(writer.get("_write_count", -1)),
                "rows": -1,
                "actor": actor,
                "model": model,
                "termination": termination,
            }
        )

    def end(self, rows: int, capacity: int) -> None:
        """Records the rows the round added; drops the rounds now wholly overwritten.

        Args:
            rows: the rows added.
            capacity: the model replay's capacity.
        """
        last = self.rounds[-1]
        last["rows"] = int(rows)
        written = last["write_count"] + last["rows"]
        self.rounds = [r for r in self.rounds if r["write_count"] + r["rows"] > written - capacity]
        used = sorted({r[k] for r in self.rounds for k in ("actor", "model", "termination")} - {-1})
        index = {old: new for new, old in enumerate(used)}
        self.params = [self.params[i] for i in used]
        for r in self.rounds:
            for k in ("actor", "model", "termination"):
                r[k] = index.get(r[k], -1)

    def state_dict(self) -> dict[str, Any]:
        """The rounds and the parameter sets (tensors, ints and lists only)."""
        return {"rounds": [dict(r) for r in self.rounds], "params": list(self.params)}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restores :meth:`state_dict`'s record.

        Args:
            state: the record.
        """
        self.rounds = [dict(r) for r in state["rounds"]]
        self.params = [dict(p) for p in state["params"]]


def policy_as_planner(
    *,
    model_env: EnvBase,
    actor: TensorDictModuleBase,
    guided: bool = True,
    value_module: TensorDictModuleBase | None = None,
) -> TensorDictModuleBase:
    """The acting policy of ``sac_mbpo``: the agent's actor itself (nothing plans).

    Takes a planner builder's arguments (:func:`~torchrl_mbmf.trainers.planning.make_planner`)
    so that the model-based loop's acting slot holds the actor.

    Keyword Args:
        model_env: the learned env (unused).
        actor: the agent's policy, returned.
        guided: unused. Defaults to ``True``.
        value_module: unused. Defaults to ``None``.

    Examples:
        >>> import torch
        >>> from tensordict.nn import TensorDictModule
        >>> actor = TensorDictModule(torch.nn.Linear(3, 1), ["observation"], ["action"])
        >>> policy_as_planner(model_env=None, actor=actor) is actor
        True
    """
    return actor


class BranchedRollouts:
    """MBPO's model rollouts and model replay (the ``mbpo`` config group's builder).

    :meth:`generate` samples ``rollout_batch_size`` start states uniformly from the real
    transitions (with replacement), rolls them ``rollout_horizon`` steps in
    :class:`RandomMemberEnv` (a single model: :class:`~torchrl_mbmf.envs.LearnedDynamicsEnv`)
    with ``actor`` sampling its actions (``ExplorationType.RANDOM``), drops every step after a
    branch's first predicted termination (the env's ``termination_fn``: the task's rule or a
    learned head) and adds the rest, as the entries ``keys``, to :attr:`replay`, a FIFO of
    ``model_replay_size`` transitions. The SAC agent mixes it with its real replay
    (:meth:`~torchrl_mbmf.trainers.agents.SACAgent.mix_model_replay`).

    Args:
        world_model: the fitted dynamics model (an ensemble for MBPO).
        env: the real env (specs, observation map and termination rule).
        actor: the agent's policy.
        keys: the entries a transition keeps (the loss's ``in_keys``).
        termination_fn: the model's terminal states (``None``: the task's rule).
            Defaults to ``None``.
        device: the model replay's device. Defaults to the CPU.

    Keyword Args:
        rollout_every: real steps between two rollout rounds.
        rollout_batch_size: branches per round (start states).
        rollout_horizon: imagined steps per branch.
        model_replay_size: imagined transitions kept (the oldest go first).
        real_ratio: share of real transitions in each update batch, in ``[0, 1]``.
        refit_every: real steps between two model refits (read by the phase schedule).

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.data import collect_random_transitions
        >>> from torchrl_mbmf.envs import make_env
        >>> from torchrl_mbmf.modules import EnsembleDeltaDynamicsModel, make_sac_actor_critic
        >>> env = make_env("Hopper-v5", seed=0)
        >>> actor, _ = make_sac_actor_critic(env, hidden_sizes=(8,))
        >>> model = EnsembleDeltaDynamicsModel(12, 3, num_members=2, hidden_sizes=(8,))
        >>> keys = ["observation", "action", ("next", "observation"), ("next", "reward"),
        ...         ("next", "done"), ("next", "terminated")]
        >>> rollouts = BranchedRollouts(model, env, actor, keys, rollout_every=250,
        ...     rollout_batch_size=20, rollout_horizon=3, model_replay_size=100,
        ...     real_ratio=0.1, refit_every=250)
        >>> data = collect_random_transitions(make_env("Hopper-v5", seed=0), 50, seed=0)
        >>> stats = rollouts.generate(data)
        >>> 20 <= len(rollouts.replay) <= 60, stats["rollout/transitions"] == len(rollouts.replay)
        (True, True)
    """

    #: The range of each argument, checked by the constructor.
    ARGUMENTS: dict[str, Setting] = settings(
        positive_int=(
            "rollout_every",
            "rollout_batch_size",
            "rollout_horizon",
            "model_replay_size",
            "refit_every",
        ),
        probability=("real_ratio",),
    )

    def __init__(
        self,
        world_model: DeltaDynamicsModel,
        env: EnvBase,
        actor: TensorDictModuleBase,
        keys: Sequence[NestedKey],
        termination_fn: TerminationFn | None = None,
        device: torch.device | str = "cpu",
        *,
        rollout_every: int,
        rollout_batch_size: int,
        rollout_horizon: int,
        model_replay_size: int,
        real_ratio: float,
        refit_every: int,
    ) -> None:
        check_arguments(self.ARGUMENTS, locals())
        self.rollout_every, self.refit_every = int(rollout_every), int(refit_every)
        self.rollout_batch_size, self.horizon = int(rollout_batch_size), int(rollout_horizon)
        self.real_ratio = float(real_ratio)
        self.keys = list(keys)
        self.actor, self.world_model, self.termination_fn = actor, world_model, termination_fn
        #: What rebuilds the model replay exactly (see :class:`RolloutRounds`).
        self.rounds = RolloutRounds()
        env_cls = RandomMemberEnv if world_model.ensemble_size > 1 else LearnedDynamicsEnv
        self.model_env = env_cls(world_model, env, termination_fn=termination_fn)
        self.replay = TensorDictReplayBuffer(
            storage=LazyTensorStorage(int(model_replay_size), device=device), batch_size=1
        )

    def due(self, real_steps: int, next_rollout: int) -> bool:
        """Whether a rollout round is due at ``real_steps`` (``next_rollout``: the next due step).

        Args:
            real_steps: real steps so far.
            next_rollout: the real step of the next round (0: none yet).
        """
        return real_steps >= next_rollout

    def imagine(self, starts: torch.Tensor) -> tuple[TensorDictBase, torch.Tensor]:
        """Rolls ``starts`` ``[N, state_dim]`` out ``rollout_horizon`` steps.

        Returns:
            The rollout ``[N, H]`` (every entry of the env's steps) and the mask ``[N, H]`` of
            the steps a branch keeps: those before its first predicted termination and that
            termination itself (with ``("next", "terminated")`` set).

        Args:
            starts: real start states.
        """
        env = self.model_env
        with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
            start = env.reset(TensorDict({env.state_key: starts}, batch_size=starts.shape[:1]))
            td = env.rollout(
                self.horizon,
                self.actor,
                tensordict=start,
                auto_reset=False,
                break_when_any_done=False,
            )
        done = td.get(("next", "terminated")).squeeze(-1).long()  # [N, H]
        # alive before step t: no termination at steps < t
        keep = (torch.cumsum(done, dim=-1) - done) == 0
        return td, keep

    def branches(self, starts: torch.Tensor) -> TensorDictBase:
        """The kept transitions of :meth:`imagine` as the entries ``keys``, flat ``[M]``.

        Args:
            starts: real start states ``[N, state_dim]``.
        """
        td, keep = self.imagine(starts)
        return td[keep].select(*self.keys)

    def generate(self, real: TransitionDataset) -> dict[str, float]:
        """One rollout round from real states of ``real``; returns the scalars to log.

        Args:
            real: the real transitions (their ``state`` entries are the start states).

        Raises:
            ValueError: if ``real`` is empty.
        """
        if len(real) == 0:
            raise ValueError("BranchedRollouts.generate: no real transitions to start from")
        states = real.tensors().get(real.state_key)
        modules = (self.actor, self.world_model, self.termination_fn)
        self.rounds.begin(states.shape[0], self.replay.writer.state_dict(), modules)
        kept = self.imagine_round(states)
        self.replay.extend(kept.to(self.replay.storage.device))
        self.rounds.end(kept.numel(), self.replay.storage.max_size)
        terminated = kept.get(("next", "terminated")).float()
        return {
            "rollout/transitions": float(kept.numel()),
            "rollout/mean_length": kept.numel() / self.rollout_batch_size,
            "rollout/terminated": float(terminated.sum()),
            "rollout/mean_reward": float(kept.get(("next", "reward")).mean()),
        }

    def imagine_round(self, states: torch.Tensor) -> TensorDictBase:
        """A round's kept transitions from start states drawn uniformly from ``states``.

        Args:
            states: the real states ``[n, state_dim]`` (drawn with replacement).
        """
        index = torch.randint(0, states.shape[0], (self.rollout_batch_size,))
        starts = states[index].to(self.model_env.device).float()
        return self.branches(starts)
