"""Episode bookkeeping of stored transitions: where episodes end, their ids, their windows."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

__all__ = ["TRAJ_KEY", "TrajectoryIds", "consecutive_windows", "episode_ends"]

#: The stored key of each transition's episode id.
TRAJ_KEY = "traj_id"


def episode_ends(batch: TensorDictBase) -> torch.Tensor:
    """Where episodes end in a batch of transitions: ``done | terminated | truncated``.

    Args:
        batch: transitions with ``("next", "done")`` and/or ``terminated`` / ``truncated``.

    Returns:
        A bool tensor of the batch's shape.

    Raises:
        KeyError: none of the three flags is present.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_mbmf.data.episodes import episode_ends
        >>> td = TensorDict(next=TensorDict(terminated=torch.tensor([[False], [True]]),
        ...                                 truncated=torch.tensor([[True], [False]])),
        ...                 batch_size=[2])
        >>> episode_ends(td).tolist()
        [True, True]
    """
    nxt = batch.get("next")
    done = nxt.get("done").clone() if "done" in nxt else None
    for key in ("terminated", "truncated"):
        if key in nxt:
            flag = nxt.get(key)
            done = flag.clone() if done is None else done | flag
    if done is None:
        raise KeyError("transitions need ('next', 'done') (or terminated/truncated)")
    return done.reshape(batch.batch_size)


class TrajectoryIds:
    """Gives each stored transition the id of its episode; episodes continue across batches.

    Each of ``N`` envs keeps an open episode id; a done step closes it and the env's next step
    opens a new one. The last step of each env in one batch and the first of the next belong
    to the same episode unless it was done.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.data.episodes import TrajectoryIds
        >>> ids = TrajectoryIds()
        >>> ids.assign(torch.tensor([[False, True, False]])).tolist()
        [[0, 0, 1]]
        >>> ids.assign(torch.tensor([[False, False]])).tolist(), ids.next_id
        ([[1, 1]], 2)
    """

    def __init__(self) -> None:
        self.next_id = 0
        self.open: torch.Tensor | None = None  # id of each env's running episode

    def assign(self, done: torch.Tensor) -> torch.Tensor:
        """The episode ids ``[N, T]`` of a batch whose done flags are ``done`` ``[N, T]``."""
        n_envs = done.shape[0]
        if self.open is None or self.open.numel() != n_envs:
            self.open = torch.arange(self.next_id, self.next_id + n_envs)
            self.next_id += n_envs
        # A new episode starts after every done step; each done opens one new id (the last
        # step's done opens the id the env continues with in the next batch).
        starts = torch.zeros_like(done, dtype=torch.long)
        starts[:, 1:] = done[:, :-1].long()
        local = starts.cumsum(1)  # 0 for the episode left open by the previous batch
        opened = done.long().sum(1)
        base = self.next_id + torch.cumsum(opened, 0) - opened
        ids = torch.where(local == 0, self.open[:, None], base[:, None] + local - 1)
        self.open = torch.where(opened > 0, base + opened - 1, self.open)
        self.next_id += int(opened.sum())
        return ids

    def state(self) -> dict[str, int | list[int] | None]:
        """The ``next_traj`` and ``open_traj`` entries of a dataset's record."""
        return {
            "next_traj": self.next_id,
            "open_traj": None if self.open is None else self.open.tolist(),
        }

    def load_state(self, next_traj: int, open_traj: list[int] | None) -> None:
        """Restores what :meth:`state` returned.

        Args:
            next_traj: the next id to open.
            open_traj: each env's open id (``None``: no batch was stored).
        """
        self.next_id = int(next_traj)
        self.open = None if open_traj is None else torch.tensor(open_traj, dtype=torch.long)


def consecutive_windows(
    traj_ids: torch.Tensor,
    done: torch.Tensor,
    state: torch.Tensor,
    next_state: torch.Tensor,
    length: int,
) -> torch.Tensor:
    """Row indices of every run of ``length`` consecutive transitions inside one episode.

    Rows are put in time order within each episode by a stable sort on ``traj_ids`` (the
    storage order of one episode is its time order). Row ``j`` is followed by row ``j'`` in a
    window only if both carry the same trajectory id, row ``j`` is not done (after it the env
    was reset), and row ``j``'s next state equals row ``j'``'s state exactly (an env reset
    between two ``extend`` calls without a done flag, e.g. by a new collector, keeps the id
    but breaks this). The last transition of a window may be done.

    Args:
        traj_ids: episode id of each row ``[N]``.
        done: done flag of each row ``[N]`` or ``[N, 1]``.
        state: state of each row ``[N, ...]``.
        next_state: next state of each row ``[N, ...]``.
        length: transitions per window (``>= 1``).

    Returns:
        A ``[W, length]`` long tensor of row indices, each row in time order; with
        ``length == 1`` every row is a window.

    Raises:
        ValueError: if ``length < 1``.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.data.episodes import consecutive_windows
        >>> state = torch.arange(6.0)[:, None]
        >>> done = torch.tensor([False, False, True, False, False, False])
        >>> consecutive_windows(torch.tensor([0, 0, 0, 1, 1, 1]), done, state, state + 1, 2)
        tensor([[0, 1],
                [1, 2],
                [3, 4],
                [4, 5]])
    """
    if length < 1:
        raise ValueError(f"window length must be >= 1, got {length}")
    traj_ids = traj_ids.reshape(-1)
    n = traj_ids.numel()
    order = torch.sort(traj_ids, stable=True).indices
    if length == 1:
        return order[:, None]
    if n < length:
        return torch.empty(0, length, dtype=torch.long)
    cur, nxt = order[:-1], order[1:]
    link = (
        (traj_ids[cur] == traj_ids[nxt])
        & ~done.reshape(-1)[cur].bool()
        & (next_state[cur] == state[nxt]).reshape(n - 1, -1).all(-1)
    )
    # broken[j]: how many of the links between positions 0..j are broken
    broken = torch.cat([torch.zeros(1, dtype=torch.long), (~link).long().cumsum(0)])
    starts = torch.arange(n - length + 1)
    starts = starts[broken[starts + length - 1] == broken[starts]]
    return order[starts[:, None] + torch.arange(length)]
