"""A transition dataset on disk: its record (metadata and checksum), its folder, its loading.

:class:`DatasetFiles` is the part of :class:`~torchrl_mbmf.data.TransitionDataset` that saves
and loads it. A saved dataset is a folder with the stored tensors (a memory-mapped TensorDict
under ``buffer/``) and ``metadata.json``: the provenance (env id, reward, seed), the counts, the
trajectory-id state, the stored keys, the package version and a SHA-256 over all of them and
every stored tensor's dtype, shape and bytes. Saving writes a temporary folder renamed into
place; loading reads JSON and raw tensor files only (nothing is unpickled) and checks the
checksum before anything is returned.

Formats: ``torchrl_mbmf.transitions/3`` stores the real env's ``("next", "terminated")`` beside
``("next", "done")``; ``/2`` (written before) has no ``terminated``, still loads, and keeps its
format (and checksum) when saved again.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Self

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey

import torchrl_mbmf
from torchrl_mbmf.data.memmap import UnsafeFolderError, load_tensor_folder

__all__ = [
    "FORMAT",
    "FORMAT_WITHOUT_TERMINATED",
    "TERMINATED_KEY",
    "CorruptDatasetError",
    "DatasetFiles",
    "DatasetMismatchError",
]

#: The format of a dataset that stores ``("next", "terminated")``.
FORMAT = "torchrl_mbmf.transitions/3"
#: The format written before (no ``terminated``: its terminal transitions are not known).
FORMAT_WITHOUT_TERMINATED = "torchrl_mbmf.transitions/2"
_KEY_COUNT = {FORMAT: 7, FORMAT_WITHOUT_TERMINATED: 6}
#: The stored key of the real env's termination flag.
TERMINATED_KEY = ("next", "terminated")
_META_FILE = "metadata.json"
_BUFFER_DIR = "buffer"
#: Entries of a dataset's record that describe the stored data, not its provenance.
_RECORD_ONLY = (
    "format",
    "num_transitions",
    "capacity",
    "next_traj",
    "open_traj",
    "sha256",
    "keys",
    "package_version",
)


class DatasetMismatchError(ValueError):
    """A saved dataset was collected under another env, reward or key layout."""


class CorruptDatasetError(RuntimeError):
    """A saved dataset is truncated or its content does not match its checksum."""


def checksum(
    meta: Mapping[str, Any], stored: TensorDictBase | None, keys: Sequence[NestedKey]
) -> str:
    """SHA-256 of a record (all but ``sha256``) and each stored tensor's dtype, shape and bytes.

    Args:
        meta: the record.
        stored: the ``[N]`` transitions (``None`` when there are none).
        keys: the stored keys, in order.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_mbmf.data.dataset_files import checksum
        >>> td = TensorDict(state=torch.zeros(2, 3), batch_size=[2])
        >>> checksum({"a": 1}, td, ["state"]) == checksum({"a": 2}, td, ["state"])
        False
    """
    digest = hashlib.sha256()
    record = {k: v for k, v in meta.items() if k != "sha256"}
    digest.update(json.dumps(record, sort_keys=True, separators=(",", ":")).encode())
    if stored is not None:
        for key in keys:
            tensor = stored.get(key).contiguous()
            digest.update(f"{key!r}:{tensor.dtype}:{list(tensor.shape)};".encode())
            digest.update(tensor.reshape(-1).view(torch.uint8).numpy())
    return digest.hexdigest()


def check_record(meta: Any, where: str, source: str) -> list[NestedKey]:
    """The stored keys of a dataset record; raises on a record of another format or shape.

    Args:
        meta: the record (``metadata.json``).
        where: the file the errors name.
        source: the data the errors name.

    Raises:
        CorruptDatasetError: the record's format is unknown, or it lacks an entry, or its keys
            do not fit its format.

    Examples:
        >>> from torchrl_mbmf.data.dataset_files import check_record
        >>> meta = {"format": "torchrl_mbmf.transitions/2", "num_transitions": 0, "sha256": "",
        ...         "next_traj": 0, "open_traj": None,
        ...         "keys": ["s", "a", ["next", "s"], ["next", "r"], ["next", "done"], "id"]}
        >>> check_record(meta, "m", "d")[3]
        ('next', 'r')
    """
    found = meta.get("format") if isinstance(meta, dict) else None
    if found not in _KEY_COUNT:
        hint = (
            " (written by an older version whose checksum did not cover the metadata: "
            "collect or save it again)"
            if found == "torchrl_mbmf.transitions/1"
            else ""
        )
        raise CorruptDatasetError(
            f"{source} has format {found!r}, expected {FORMAT!r} or "
            f"{FORMAT_WITHOUT_TERMINATED!r}{hint}"
        )
    required = ("num_transitions", "sha256", "keys", "next_traj", "open_traj")
    missing = [k for k in required if k not in meta]
    if missing:
        raise CorruptDatasetError(f"{where} lacks the entries {missing}")
    keys = [tuple(k) if isinstance(k, list) else k for k in meta["keys"]]
    valid = (
        len(keys) == _KEY_COUNT[found]
        and isinstance(keys[3], tuple)
        and len(keys[3]) == 2
        and (found != FORMAT or keys[5] == TERMINATED_KEY)
    )
    if not valid:
        raise CorruptDatasetError(f"{where} has an invalid key list {meta['keys']!r}")
    return keys


class DatasetFiles:
    """Saving, recording and loading of a :class:`~torchrl_mbmf.data.TransitionDataset`.

    A base of the dataset class: it reads the dataset's ``metadata``, ``capacity``, ``keys``,
    ``tensors()``, ``episodes`` and ``stores_terminated`` and builds new datasets with the
    dataset class's constructor.

    Examples:
        >>> from torchrl_mbmf.data import TransitionDataset
        >>> from torchrl_mbmf.data.dataset_files import DatasetFiles
        >>> issubclass(TransitionDataset, DatasetFiles)
        True
    """

    def save(self, path: str | os.PathLike, *, overwrite: bool = False) -> Path:
        """Writes the dataset to the folder ``path`` atomically.

        Args:
            path: target folder.

        Keyword Args:
            overwrite: replace an existing dataset at ``path``. Defaults to ``False``.

        Returns:
            The path.

        Raises:
            FileExistsError: if ``path`` exists and ``overwrite`` is ``False``.

        Examples:
            >>> import tempfile
            >>> from pathlib import Path
            >>> from torchrl_mbmf.data import TransitionDataset, collect_random_transitions
            >>> from torchrl_mbmf.envs import env_metadata, make_gym_state_env
            >>> env = make_gym_state_env("Pendulum-v1")
            >>> data = collect_random_transitions(env, 30, seed=0)
            >>> with tempfile.TemporaryDirectory() as d:
            ...     path = data.save(Path(d) / "random")
            ...     loaded = TransitionDataset.load(path, expect=env_metadata(env))
            >>> len(loaded), loaded.metadata["env_id"]
            (30, 'Pendulum-v1')
        """
        path = Path(path)
        if path.exists() and not overwrite:
            raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent))
        try:
            if len(self):
                self.tensors().select(*self.keys).memmap(tmp / _BUFFER_DIR)
            meta = self.record()
            (tmp / _META_FILE).write_text(json.dumps(meta, indent=2, sort_keys=True))
            if path.exists():
                old = path.with_name(path.name + ".old")
                shutil.rmtree(old, ignore_errors=True)
                os.replace(path, old)
                os.replace(tmp, path)
                shutil.rmtree(old, ignore_errors=True)
            else:
                os.replace(tmp, path)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return path

    def record(self) -> dict[str, Any]:
        """The metadata :meth:`save` writes (``metadata.json``), with the checksum of the data.

        Returns:
            A JSON-compatible dict (its ``"sha256"`` entry is the checksum), from which and the
            tensors :meth:`from_record` rebuilds the dataset.

        Examples:
            >>> from torchrl_mbmf.data import collect_random_transitions
            >>> from torchrl_mbmf.envs import make_gym_state_env
            >>> data = collect_random_transitions(make_gym_state_env("Pendulum-v1"), 30, seed=0)
            >>> record = data.record()
            >>> record["num_transitions"], record["format"], len(record["sha256"])
            (30, 'torchrl_mbmf.transitions/3', 64)
        """
        meta = {
            **self.metadata,
            "format": FORMAT if self.stores_terminated else FORMAT_WITHOUT_TERMINATED,
            "num_transitions": len(self),
            "capacity": self.capacity,
            **self.episodes.state(),
            "keys": [list(k) if isinstance(k, tuple) else k for k in self.keys],
            "package_version": torchrl_mbmf.__version__,
        }
        # the checksum is taken over the metadata as it will be read back (JSON types)
        meta = json.loads(json.dumps(meta))
        meta["sha256"] = self._checksum(meta)
        return meta

    def _checksum(self, meta: Mapping[str, Any]) -> str:
        return checksum(meta, self.tensors() if len(self) else None, self.keys)

    def dumps(self, path: str | os.PathLike) -> None:
        """Saves into ``path`` for ``torchrl.checkpoint`` (same files as :meth:`save`)."""
        self.save(path, overwrite=True)

    def loads(self, path: str | os.PathLike) -> None:
        """Restores in place from :meth:`dumps` output, checking env, reward and checksum."""
        other = type(self).load(
            path,
            expect={"env_id": self.metadata["env_id"], "reward": self.metadata["reward"]},
            capacity=self.capacity,
            scratch_dir=self._scratch,
        )
        self.__dict__.update(
            {k: other.__dict__[k] for k in ("buffer", "episodes", "metadata", "_terminated")}
        )
        self._layout = None  # read again from the stored transitions at the next extend

    @classmethod
    def load(
        cls,
        path: str | os.PathLike,
        *,
        expect: Mapping[str, Any] | None = None,
        capacity: int | None = None,
        scratch_dir: str | os.PathLike | None = None,
    ) -> Self:
        """Loads a dataset written by :meth:`save`, checking provenance and integrity.

        Args:
            path: the folder.

        Keyword Args:
            expect: metadata entries that must match (typically ``env_metadata(env)``: env id
                and reward parameters). Defaults to no check.
            capacity: capacity of the loaded dataset. Defaults to the saved one or the number of
                transitions, whichever is larger.
            scratch_dir: folder of the memory-mapped files. Defaults to a temporary folder.

        Returns:
            The dataset.

        Raises:
            FileNotFoundError: if there is no dataset at ``path``.
            DatasetMismatchError: if an ``expect`` entry differs (the message names it).
            CorruptDatasetError: if files are missing (the message names them), truncated,
                hold anything but the expected plain tensors, or fail the checksum (which
                covers the metadata too).
        """
        meta, stored = _read_folder(Path(path))
        return cls.from_record(
            meta,
            stored,
            expect=expect,
            capacity=capacity,
            scratch_dir=scratch_dir,
            source=str(path),
        )

    @classmethod
    def from_record(
        cls,
        record: Mapping[str, Any],
        stored: TensorDictBase | None,
        *,
        expect: Mapping[str, Any] | None = None,
        capacity: int | None = None,
        scratch_dir: str | os.PathLike | None = None,
        source: str = "the record",
    ) -> Self:
        """A dataset from its :meth:`record` and its stored tensors, checked against the record.

        :meth:`load` reads both from a saved folder; a dataset rebuilt another way (replaying
        its actions, :class:`~torchrl_mbmf.runs.dataset_replay.DatasetReplay`) is checked the
        same way.

        Args:
            record: the metadata of :meth:`record` (``metadata.json``).
            stored: the ``[N]`` transitions (:attr:`keys`; ``None`` when ``N`` is 0).

        Keyword Args:
            expect: metadata entries that must match. Defaults to no check.
            capacity: capacity of the dataset. Defaults to the recorded one or ``N``, whichever
                is larger.
            scratch_dir: folder of the memory-mapped files. Defaults to a temporary folder.
            source: what the error messages call the data. Defaults to ``"the record"``.

        Returns:
            The dataset.

        Raises:
            CorruptDatasetError: if the record is invalid, the tensors are not ``N``
                transitions, or either fails the checksum.
            DatasetMismatchError: if an ``expect`` entry differs.

        Examples:
            >>> from torchrl_mbmf.data import TransitionDataset, collect_random_transitions
            >>> from torchrl_mbmf.envs import make_gym_state_env
            >>> data = collect_random_transitions(make_gym_state_env("Pendulum-v1"), 30, seed=0)
            >>> copy = TransitionDataset.from_record(data.record(), data.tensors().clone())
            >>> len(copy), copy.record()["sha256"] == data.record()["sha256"]
            (30, True)
        """
        meta = dict(record)
        keys = check_record(meta, source, source)
        n = int(meta["num_transitions"])
        provenance = {k: v for k, v in meta.items() if k not in _RECORD_ONLY}
        data = cls(
            provenance,
            capacity=max(capacity or int(meta.get("capacity", 0)), n, 1),
            scratch_dir=scratch_dir,
            state_key=keys[0],
            action_key=keys[1],
            reward_key=keys[3][1],
        )
        data._terminated = TERMINATED_KEY in keys
        data.metadata["package_version"] = meta.get("package_version")
        if n:
            if stored is None or stored.batch_size != (n,):
                found = None if stored is None else tuple(stored.batch_size)
                raise CorruptDatasetError(
                    f"{source} holds {found} transitions, its metadata says {n}"
                )
            absent = [k for k in data.keys if k not in stored.keys(True, True)]
            if absent:
                raise CorruptDatasetError(f"{source} lacks the entries {absent}")
            data.buffer.extend(stored.select(*data.keys))
        if data._checksum(meta) != meta["sha256"]:
            raise CorruptDatasetError(
                f"{source}: stored transitions or metadata do not match their checksum"
            )
        for key, value in (expect or {}).items():
            if meta.get(key) != value:
                raise DatasetMismatchError(
                    f"dataset at {source} was collected with {key}={meta.get(key)!r}, "
                    f"expected {key}={value!r}; collect new data for this configuration"
                )
        data.episodes.load_state(meta["next_traj"], meta["open_traj"])
        return data


def _read_folder(path: Path) -> tuple[dict[str, Any], TensorDictBase | None]:
    """The record and stored tensors of a saved dataset (:meth:`DatasetFiles.load`'s reading)."""
    meta_file = path / _META_FILE
    if not meta_file.exists():
        raise FileNotFoundError(f"no dataset at {path} (missing {_META_FILE})")
    try:
        meta = json.loads(meta_file.read_text())
    except json.JSONDecodeError as err:
        raise CorruptDatasetError(f"{meta_file} is not valid JSON: {err}") from err
    keys = check_record(meta, str(meta_file), str(path))
    stored = None
    if int(meta["num_transitions"]):
        try:
            # JSON and raw tensor files only: nothing stored is ever unpickled
            stored = load_tensor_folder(path / _BUFFER_DIR, keys=keys)
        except UnsafeFolderError as err:
            raise CorruptDatasetError(f"cannot read the buffer of {path}: {err}") from err
        absent = [k for k in keys if k not in stored.keys(True, True)]
        if absent:
            raise CorruptDatasetError(
                f"cannot read the buffer of {path}: "
                f"{path / _BUFFER_DIR / 'meta.json'} lacks the entries {absent}"
            )
    return meta, stored
