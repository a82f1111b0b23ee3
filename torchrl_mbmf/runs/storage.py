"""How a checkpoint folder is written and checked: integrity records and pickle-free adapters.

:class:`SealedWriter` writes a checkpoint with an integrity record, :func:`verify_checkpoint`
checks it before any restore, :func:`latest_intact_checkpoint` picks the newest intact one; the
adapters restore every component without pickle. Why: ``docs/design/run_folder.md``.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import shutil
import uuid
import warnings
from collections import OrderedDict
from collections.abc import Collection, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict.utils import NestedKey
from torchrl.checkpoint import (
    Checkpoint,
    CheckpointAdapter,
    CheckpointOptions,
    CheckpointRotation,
)

from torchrl_mbmf.data.memmap import (
    UnsafeFolderError,
    is_stored_shape,
    load_tensor_folder,
    stored_dtype,
)

__all__ = [
    "INTEGRITY_FILE",
    "CheckpointIntegrityError",
    "DamagedCheckpointWarning",
    "DatasetCheckpointAdapter",
    "ReplayCheckpointAdapter",
    "SealedWriter",
    "TensorStateAdapter",
    "changed_files",
    "latest_intact_checkpoint",
    "read_tensor_state",
    "reseal_files",
    "verify_checkpoint",
    "write_integrity_record",
]

logger = logging.getLogger(__name__)

INTEGRITY_FILE = "integrity.json"
_INTEGRITY_FORMAT = "torchrl_mbmf.checkpoint_integrity/1"
_DAMAGED_DIR = "damaged"


class CheckpointIntegrityError(RuntimeError):
    """A checkpoint is damaged (a file missing, changed, truncated or added) or unverifiable."""


class DamagedCheckpointWarning(UserWarning):
    """A damaged checkpoint was skipped in favour of an older intact one."""


# ----------------------------------------------------------------- integrity
def _sha256(file: Path) -> str:
    with file.open("rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def _files_below(root: Path) -> list[Path]:
    return sorted(p for p in root.rglob("*") if not p.is_dir() or p.is_symlink())


def write_integrity_record(path: str | os.PathLike) -> Path:
    """Writes ``integrity.json``: the size and SHA-256 of every other file below ``path``.

    :class:`SealedWriter` calls it last, inside its staging folder, before the rename.

    Args:
        path: the checkpoint folder.

    Returns:
        The record's path.

    Examples:
        >>> import json, tempfile
        >>> from pathlib import Path
        >>> from torchrl_mbmf.runs.storage import write_integrity_record
        >>> with tempfile.TemporaryDirectory() as d:
        ...     _ = (Path(d) / "a.txt").write_text("hi")
        ...     record = json.loads(write_integrity_record(d).read_text())
        >>> record["files"]["a.txt"]["bytes"]
        2
    """
    root = Path(path)
    files = {}
    for file in _files_below(root):
        if file.name == INTEGRITY_FILE and file.parent == root:
            continue
        if file.is_symlink():
            raise CheckpointIntegrityError(f"refusing to checkpoint the symbolic link {file}")
        files[file.relative_to(root).as_posix()] = {
            "bytes": file.stat().st_size,
            "sha256": _sha256(file),
        }
    record = {"format": _INTEGRITY_FORMAT, "files": files}
    with (root / INTEGRITY_FILE).open("w", encoding="utf-8") as f:
        json.dump(record, f, indent=1, sort_keys=True)
        f.flush()
        os.fsync(f.fileno())
    return root / INTEGRITY_FILE


def verify_checkpoint(path: str | os.PathLike, *, compacted: Collection[str] = ()) -> None:
    """Checks every file of a checkpoint against its integrity record.

    The record (``integrity.json``, written last by :class:`SealedWriter`) lists each
    file's size and SHA-256. A file that is missing, of another size or content, a file the
    record does not list, a symbolic link, or a missing or unreadable record all fail.

    Args:
        path: the checkpoint folder.

    Keyword Args:
        compacted: names of folders that hold a compact record in place of files (``replay``,
            ``rebuild``): files below such a folder need not be listed, and listed files
            missing beside one are not yet rebuilt. Defaults to none: every file is checked.

    Raises:
        CheckpointIntegrityError: naming the first damaged file.

    Examples:
        >>> import tempfile, torch
        >>> from pathlib import Path
        >>> from torchrl_mbmf.runs.storage import (
        ...     CheckpointIntegrityError, TensorStateAdapter, SealedWriter, verify_checkpoint)
        >>> checkpoint = SealedWriter()
        >>> _ = checkpoint.register("net", torch.nn.Linear(2, 1), adapter=TensorStateAdapter())
        >>> with tempfile.TemporaryDirectory() as d:
        ...     path = checkpoint.save(Path(d) / "ckpt")
        ...     verify_checkpoint(path)
        ...     weight = next(path.rglob("*.bin"))
        ...     weight.write_bytes(weight.read_bytes()[:3])
        ...     try:
        ...         verify_checkpoint(path)
        ...     except CheckpointIntegrityError as err:
        ...         print("damaged:", weight.name in str(err))
        3
        damaged: True
    """
    root = Path(path)
    record_file = root / INTEGRITY_FILE
    if not root.is_dir():
        raise CheckpointIntegrityError(f"checkpoint {root} is not a folder")
    if record_file.is_symlink() or not record_file.is_file():
        raise CheckpointIntegrityError(
            f"checkpoint {root} has no integrity record {INTEGRITY_FILE} (an interrupted or "
            "foreign save); it cannot be verified"
        )
    try:
        record = json.loads(record_file.read_text(encoding="utf-8"))
        files = record["files"]
        if record.get("format") != _INTEGRITY_FORMAT or not isinstance(files, dict):
            raise ValueError(f"format {record.get('format')!r}")
    except (UnicodeDecodeError, ValueError, KeyError, TypeError, AttributeError) as err:
        raise CheckpointIntegrityError(f"{record_file} is damaged: {err}") from err
    present = {p.relative_to(root).as_posix(): p for p in _files_below(root) if p != record_file}
    # the folders that hold a compact record (a subfolder named in ``compacted``)
    holders = {
        parent.parent
        for name in present
        for parent in Path(name).parents
        if parent.name and parent.name in compacted
    }
    for name in sorted(set(present) - set(files)):
        if not set(Path(name).parent.parts) & set(compacted):
            raise CheckpointIntegrityError(
                f"{root / name} is not listed in {record_file} (added after the save)"
            )
    for name, entry in sorted(files.items()):
        file = root / name
        if name not in present and any(h in Path(name).parents for h in holders):
            continue  # rebuilt from the compact record beside it
        if name not in present:
            raise CheckpointIntegrityError(f"{file} is missing (listed in {record_file})")
        if file.is_symlink():
            raise CheckpointIntegrityError(f"{file} is a symbolic link")
        if not isinstance(entry, dict):
            raise CheckpointIntegrityError(f"{record_file} has an invalid entry for {name!r}")
        size = file.stat().st_size
        if size != entry.get("bytes"):
            raise CheckpointIntegrityError(
                f"{file} has {size} bytes, its record says {entry.get('bytes')} (truncated or "
                "extended)"
            )
        if _sha256(file) != entry.get("sha256"):
            raise CheckpointIntegrityError(f"{file} does not match its SHA-256 (content changed)")


def _record(root: Path) -> tuple[Path, dict[str, Any]]:
    record_file = root / INTEGRITY_FILE
    try:
        record = json.loads(record_file.read_text(encoding="utf-8"))
        if record.get("format") != _INTEGRITY_FORMAT or not isinstance(record["files"], dict):
            raise ValueError(f"format {record.get('format')!r}")
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError) as err:
        raise CheckpointIntegrityError(f"{record_file} is missing or damaged: {err}") from err
    return record_file, record


def changed_files(path: str | os.PathLike) -> list[str]:
    """Every file of a checkpoint that differs from its integrity record (none: it verifies).

    Where :func:`verify_checkpoint` stops at the first damaged file, this lists them all:
    listed files that are missing, of another size or content, and files the record does not
    list, as paths relative to the checkpoint.

    Args:
        path: the checkpoint folder.

    Raises:
        CheckpointIntegrityError: if the record is missing or unreadable.

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from torchrl_mbmf.runs.storage import changed_files, write_integrity_record
        >>> with tempfile.TemporaryDirectory() as d:
        ...     _ = (Path(d) / "a.txt").write_text("hi")
        ...     _ = (Path(d) / "b.txt").write_text("yo")
        ...     _ = write_integrity_record(d)
        ...     _ = (Path(d) / "b.txt").write_text("changed")
        ...     print(changed_files(d))
        ['b.txt']
    """
    root = Path(path)
    record_file, record = _record(root)
    present = {p.relative_to(root).as_posix(): p for p in _files_below(root) if p != record_file}
    changed = set(present) - set(record["files"])
    for name, entry in record["files"].items():
        file = present.get(name)
        if (
            file is None
            or file.is_symlink()
            or not isinstance(entry, dict)
            or file.stat().st_size != entry.get("bytes")
            or _sha256(file) != entry.get("sha256")
        ):
            changed.add(name)
    return sorted(changed)


def reseal_files(path: str | os.PathLike, names: Collection[str]) -> None:
    """Writes the present size and SHA-256 of the named files into a checkpoint's record.

    For a deliberate, recorded change of a few files (a model replay re-run on another CPU,
    accepted by its caller); every other entry is kept, so :func:`verify_checkpoint` still
    checks the rest as saved.

    Args:
        path: the checkpoint folder.
        names: files relative to the checkpoint, each already listed in its record.

    Raises:
        CheckpointIntegrityError: if the record is unreadable, or a name is not listed in it,
            is missing or is a symbolic link (nothing is written then).

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from torchrl_mbmf.runs.storage import (
        ...     reseal_files, verify_checkpoint, write_integrity_record)
        >>> with tempfile.TemporaryDirectory() as d:
        ...     _ = (Path(d) / "a.txt").write_text("hi")
        ...     _ = write_integrity_record(d)
        ...     _ = (Path(d) / "a.txt").write_text("changed")
        ...     reseal_files(d, ["a.txt"])
        ...     verify_checkpoint(d)
    """
    root = Path(path)
    record_file, record = _record(root)
    for name in names:
        file = root / name
        if name not in record["files"] or file.is_symlink() or not file.is_file():
            raise CheckpointIntegrityError(
                f"{file} cannot be resealed: it must be a plain file listed in {record_file}"
            )
        record["files"][name] = {"bytes": file.stat().st_size, "sha256": _sha256(file)}
    with record_file.open("w", encoding="utf-8") as f:
        json.dump(record, f, indent=1, sort_keys=True)
        f.flush()
        os.fsync(f.fileno())


class SealedWriter(Checkpoint):
    """A ``torchrl.checkpoint.Checkpoint`` whose saves carry an integrity record.

    ``save`` writes into a hidden staging folder, adds ``integrity.json`` (size and SHA-256 of
    every file) last and renames the folder into place. Only the ``"directory"`` format is
    supported. Loading is torchrl's; verify first (:func:`verify_checkpoint`).

    Keyword Args:
        **kwargs: as :class:`torchrl.checkpoint.Checkpoint` (components, ``strict``, ...).

    Examples:
        >>> import tempfile, torch
        >>> from pathlib import Path
        >>> from torchrl_mbmf.runs.storage import TensorStateAdapter, SealedWriter
        >>> source, target = torch.nn.Linear(2, 1), torch.nn.Linear(2, 1)
        >>> with tempfile.TemporaryDirectory() as d:
        ...     saver = SealedWriter().register("net", source, adapter=TensorStateAdapter())
        ...     path = saver.save(Path(d) / "ckpt")
        ...     loader = SealedWriter().register("net", target, adapter=TensorStateAdapter())
        ...     print(sorted(loader.load(path).loaded), (path / "integrity.json").exists())
        ['net'] True
        >>> torch.equal(source.weight, target.weight)
        True
    """

    def __init__(self, **kwargs: Any) -> None:
        if kwargs.get("format", "directory") != "directory":
            raise ValueError(f"SealedWriter writes folders only, got format={kwargs['format']!r}")
        super().__init__(**kwargs)

    def save(
        self,
        path: str | Path,
        *,
        components: Collection[str] | None = None,
        component_options: Mapping[str, CheckpointOptions] | None = None,
        format: str | None = None,
        metadata: Mapping[str, Any] | None = None,
    ) -> Path:
        """Saves atomically, with the integrity record written last.

        Args:
            path: the checkpoint folder.

        Keyword Args:
            components: as :meth:`torchrl.checkpoint.Checkpoint.save`.
            component_options: as :meth:`torchrl.checkpoint.Checkpoint.save`.
            format: ``None`` or ``"directory"``.
            metadata: as :meth:`torchrl.checkpoint.Checkpoint.save`.

        Returns:
            The checkpoint folder.

        Examples:
            >>> import tempfile
            >>> from pathlib import Path
            >>> from torchrl_mbmf.runs.storage import SealedWriter
            >>> with tempfile.TemporaryDirectory() as d:
            ...     path = SealedWriter(progress={"step": 3}).save(Path(d) / "c")
            ...     print(sorted(p.name for p in path.iterdir()))
            ['components', 'integrity.json', 'manifest.json']
        """
        if format not in (None, "directory"):
            raise ValueError(f"SealedWriter writes folders only, got format={format!r}")
        destination = Path(path).expanduser().absolute()
        destination.parent.mkdir(parents=True, exist_ok=True)
        token = uuid.uuid4().hex
        stage = destination.parent / f".{destination.name}.verify-{token}"
        replaced = destination.parent / f".{destination.name}.replaced-{token}"
        try:
            super().save(
                stage,
                components=components,
                component_options=component_options,
                format="directory",
                metadata=metadata,
            )
            write_integrity_record(stage)
            if destination.exists():
                os.replace(destination, replaced)
            os.replace(stage, destination)
        finally:
            for leftover in (stage, replaced):
                if leftover.exists():
                    shutil.rmtree(leftover, ignore_errors=True)
        return destination


def _remove_staging_leftovers(directory: Path, prefix: str) -> None:
    """Removes hidden folders/files an interrupted save or prune left (never loaded)."""
    # torchrl's own staging of a SealedWriter save is named "..<prefix>-<step>..."
    staging = re.compile(rf"\.+{re.escape(prefix)}-\d+\..+")
    for entry in directory.iterdir():
        if staging.fullmatch(entry.name):
            logger.info("removing %s, left by an interrupted checkpoint save", entry)
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry, ignore_errors=True)
            else:
                entry.unlink(missing_ok=True)


def latest_intact_checkpoint(rotation: CheckpointRotation) -> Path | None:
    """The newest checkpoint of a rotation folder that passes :func:`verify_checkpoint`.

    Staging leftovers of interrupted saves are removed first. A damaged checkpoint newer than
    the one returned is moved into a ``damaged`` subfolder with a
    :class:`DamagedCheckpointWarning` naming the damaged file.

    Args:
        rotation: the run's checkpoint rotation (folder and name prefix).

    Returns:
        The checkpoint folder, or ``None`` when the folder holds no checkpoint at all.

    Raises:
        CheckpointIntegrityError: when there are checkpoints but none is intact (they are
            left in place; the message names each damaged file).

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from torchrl.checkpoint import CheckpointRotation
        >>> from torchrl_mbmf.runs.storage import (
        ...     SealedWriter, latest_intact_checkpoint)
        >>> with tempfile.TemporaryDirectory() as d:
        ...     rotation = CheckpointRotation(Path(d), keep_last=2)
        ...     for step in (1, 2):
        ...         _ = rotation.save(SealedWriter(progress={"step": step}), step=step)
        ...     (rotation.latest() / "manifest.json").write_text("{}")  # damage the newest
        ...     import warnings
        ...     with warnings.catch_warnings(record=True) as caught:
        ...         warnings.simplefilter("always")
        ...         print(latest_intact_checkpoint(rotation).name, len(caught))
        2
        checkpoint-000000000001 1
    """
    directory = Path(rotation.directory)
    if not directory.is_dir():
        return None
    _remove_staging_leftovers(directory, rotation.prefix)
    pattern = re.compile(rf"{re.escape(rotation.prefix)}-(\d+)")
    candidates = sorted(
        (
            (int(m.group(1)), entry)
            for entry in directory.iterdir()
            if (m := pattern.fullmatch(entry.name)) and entry.is_dir()
        ),
        reverse=True,
    )
    if not candidates:
        return None
    damaged: list[tuple[Path, CheckpointIntegrityError]] = []
    for _, path in candidates:
        try:
            verify_checkpoint(path)
        except CheckpointIntegrityError as err:
            damaged.append((path, err))
            continue
        for bad, err in damaged:
            aside = directory / _DAMAGED_DIR / f"{bad.name}-{uuid.uuid4().hex[:8]}"
            aside.parent.mkdir(exist_ok=True)
            os.replace(bad, aside)
            message = (
                f"checkpoint {bad.name} is damaged ({err}); resuming from the older {path.name}"
                f" instead; the damaged one was moved to {aside}"
            )
            logger.warning(message)
            warnings.warn(message, DamagedCheckpointWarning, stacklevel=2)
        return path
    raise CheckpointIntegrityError(
        f"no intact checkpoint in {directory}: "
        + "; ".join(f"{path.name}: {err}" for path, err in damaged)
        + ". Restore a good copy, or remove the folder to start the run again."
    )


# ------------------------------------------------------------- state dicts
def _encode(value: Any, tensors: list[torch.Tensor], where: str) -> Any:
    if isinstance(value, torch.Tensor):
        dtype = str(value.dtype).removeprefix("torch.")
        if stored_dtype(dtype) is None:
            raise TypeError(
                f"{where}: a {value.dtype} tensor cannot be checkpointed by TensorStateAdapter "
                "(plain numeric and bool dtypes only)"
            )
        tensors.append(value.detach())
        return {
            "kind": "tensor",
            "index": len(tensors) - 1,
            "dtype": dtype,
            "shape": list(value.shape),
            "device": str(value.device),
        }
    if isinstance(value, Mapping):
        out: dict[str, Any] = {
            "kind": "dict",
            "ordered": isinstance(value, OrderedDict),
            "items": [
                [_encode(k, tensors, where), _encode(v, tensors, f"{where}[{k!r}]")]
                for k, v in value.items()
            ],
        }
        metadata = getattr(value, "_metadata", None)
        if metadata is not None:
            out["ordered"] = True
            out["metadata"] = _encode(metadata, tensors, f"{where}._metadata")
        return out
    if isinstance(value, (list, tuple)):
        return {
            "kind": "tuple" if isinstance(value, tuple) else "list",
            "items": [_encode(v, tensors, f"{where}[{i}]") for i, v in enumerate(value)],
        }
    if isinstance(value, np.generic):
        value = value.item()
    if value is None or isinstance(value, (bool, int, float, str)):
        return {"kind": "value", "value": value}
    raise TypeError(
        f"{where}: a {type(value).__name__} cannot be checkpointed by TensorStateAdapter "
        "(tensors, dicts, lists, tuples, None, bool, int, float and str only)"
    )


class _Decoder:
    def __init__(self, folder: Path, schema_file: Path) -> None:
        self.folder = folder
        self.schema_file = schema_file
        self.used: set[str] = set()

    def fail(self, what: str) -> ValueError:
        return ValueError(f"{self.schema_file}: {what}; refusing to load it")

    def tensor(self, spec: Mapping[str, Any]) -> torch.Tensor:
        dtype = stored_dtype(spec.get("dtype"))
        shape, index = spec.get("shape"), spec.get("index")
        if (
            dtype is None
            or not isinstance(index, int)
            or isinstance(index, bool)
            or index < 0
            or not is_stored_shape(shape)
        ):
            raise self.fail(f"invalid tensor entry {dict(spec)!r}")
        name = f"t{index:05d}.bin"
        file = self.folder / name
        if file.is_symlink() or not file.is_file():
            raise ValueError(f"missing file {file} (listed in {self.schema_file})")
        expected = int(np.prod(shape, dtype=np.int64)) * torch.empty((), dtype=dtype).element_size()
        if file.stat().st_size != expected:
            raise ValueError(
                f"{file} has {file.stat().st_size} bytes, expected {expected} for a "
                f"{tuple(shape)} {spec['dtype']} tensor"
            )
        self.used.add(name)
        raw = torch.from_numpy(np.fromfile(file, dtype=np.uint8))
        tensor = raw.view(dtype).reshape(shape)
        try:
            device = torch.device(spec.get("device", "cpu"))
        except (RuntimeError, TypeError) as err:
            raise self.fail(f"invalid device {spec.get('device')!r}") from err
        return tensor if device.type == "cpu" else tensor.to(device)

    def __call__(self, value: Any) -> Any:
        if not isinstance(value, dict):
            raise self.fail(f"invalid entry {value!r}")
        kind = value.get("kind")
        if kind == "tensor":
            return self.tensor(value)
        if kind == "value":
            item = value.get("value")
            if item is not None and not isinstance(item, (bool, int, float, str)):
                raise self.fail(f"invalid value {item!r}")
            return item
        if kind in ("list", "tuple"):
            items = value.get("items")
            if not isinstance(items, list):
                raise self.fail(f"invalid {kind} entry")
            decoded = [self(v) for v in items]
            return tuple(decoded) if kind == "tuple" else decoded
        if kind == "dict":
            items = value.get("items")
            if not isinstance(items, list) or not all(
                isinstance(p, list) and len(p) == 2 for p in items
            ):
                raise self.fail("invalid dict entry")
            out: dict = OrderedDict() if value.get("ordered") else {}
            for k, v in items:
                key = self(k)
                if isinstance(key, list):
                    raise self.fail(f"invalid dict key {key!r}")
                out[key] = self(v)
            if "metadata" in value:
                if not isinstance(out, OrderedDict):
                    raise self.fail("metadata on an unordered dict")
                out._metadata = self(value["metadata"])  # type: ignore[attr-defined]
            return out
        raise self.fail(f"unknown entry kind {kind!r}")


def read_tensor_state(path: str | os.PathLike) -> Any:
    """The state a :class:`TensorStateAdapter` wrote to the folder ``path`` (no pickle).

    Args:
        path: the component's folder.

    Raises:
        ValueError: on a missing, unlisted or wrongly sized file or an unknown entry.

    Examples:
        >>> import tempfile, torch
        >>> with tempfile.TemporaryDirectory() as d:
        ...     TensorStateAdapter().save(torch.nn.Linear(3, 2), Path(d), args=(), kwargs={})
        ...     state = read_tensor_state(d)
        >>> sorted(state), state["weight"].shape
        (['bias', 'weight'], torch.Size([2, 3]))
    """
    path = Path(path)
    schema_file = path / TensorStateAdapter.schema_filename
    if schema_file.is_symlink() or not schema_file.is_file():
        raise ValueError(f"missing file {schema_file}")
    try:
        schema = json.loads(schema_file.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{schema_file} is not valid JSON: {err}") from err
    decode = _Decoder(path, schema_file)
    state = decode(schema)
    for entry in path.iterdir():
        if entry.name != schema_file.name and entry.name not in decode.used:
            raise ValueError(
                f"unexpected file {entry} (not a tensor listed in {schema_file}); "
                "refusing to load it"
            )
    return state


class TensorStateAdapter(CheckpointAdapter):
    """Checkpoints a ``state_dict``/``load_state_dict`` object without pickle.

    The state is written as a JSON schema (``state.json``: dicts, lists, tuples, scalars and
    strings, each tensor by index, dtype, shape and device) and one raw file per tensor
    (``t00000.bin``...). Loading parses the JSON and reads each tensor from exactly
    ``numel * itemsize`` bytes; any unknown entry, missing, unlisted or wrongly sized file is
    refused with an error naming the file. Used for modules, optimisers,
    :class:`~torchrl.checkpoint.GlobalRNGState` and loggers.

    Examples:
        >>> import tempfile, torch
        >>> from pathlib import Path
        >>> from torchrl_mbmf.runs.storage import TensorStateAdapter
        >>> source, target = torch.nn.Linear(3, 2), torch.nn.Linear(3, 2)
        >>> with tempfile.TemporaryDirectory() as d:
        ...     TensorStateAdapter().save(source, Path(d), args=(), kwargs={})
        ...     TensorStateAdapter().load(target, Path(d))
        >>> torch.equal(source.bias, target.bias)
        True
    """

    adapter_id = "torchrl_mbmf.tensor_state"
    format_version = 1
    schema_filename = "state.json"

    def save(self, component: Any, path: Path, *, args: tuple, kwargs: Mapping[str, Any]) -> Any:
        """Writes ``component.state_dict()`` below ``path``.

        Args:
            component: the object.
            path: its folder.

        Keyword Args:
            args: positional arguments of ``state_dict``.
            kwargs: keyword arguments of ``state_dict``.
        """
        state = component.state_dict(*args, **kwargs)
        tensors: list[torch.Tensor] = []
        schema = _encode(state, tensors, type(component).__name__)  # refuses before writing
        path.mkdir(parents=True, exist_ok=True)
        for i, tensor in enumerate(tensors):
            flat = tensor.detach().cpu().contiguous().reshape(-1).view(torch.uint8)
            (path / f"t{i:05d}.bin").write_bytes(flat.numpy().tobytes())
        with (path / self.schema_filename).open("w", encoding="utf-8") as f:
            json.dump(schema, f, separators=(",", ":"))

    def load(self, component: Any, path: Path, **kwargs: Any) -> None:
        """Restores ``component`` from ``path`` (no pickle).

        Args:
            component: the object.
            path: its folder.

        Keyword Args:
            **kwargs: torchrl's load options (``map_location``, ``args``, ``kwargs``; the
                tensors go back to the device they were saved from).
        """
        state = read_tensor_state(path)
        component.load_state_dict(state, *kwargs.get("args", ()), **kwargs.get("kwargs", {}))


# ------------------------------------------------------- dataset and replay
class DatasetCheckpointAdapter(CheckpointAdapter):
    """Checkpoints a :class:`~torchrl_mbmf.data.TransitionDataset` in its own format.

    ``dumps``/``loads`` write and read the dataset's atomic, checksummed folder; loading
    never unpickles (see :meth:`~torchrl_mbmf.data.TransitionDataset.load`).

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from torchrl_mbmf.data import collect_random_transitions
        >>> from torchrl_mbmf.envs import make_gym_state_env
        >>> from torchrl_mbmf.runs.storage import DatasetCheckpointAdapter
        >>> env = make_gym_state_env("Pendulum-v1")
        >>> source = collect_random_transitions(env, 20, seed=0)
        >>> target = collect_random_transitions(env, 5, seed=1)
        >>> with tempfile.TemporaryDirectory() as d:
        ...     DatasetCheckpointAdapter().save(source, Path(d), args=(), kwargs={})
        ...     DatasetCheckpointAdapter().load(target, Path(d))
        >>> len(target)
        20
    """

    adapter_id = "torchrl_mbmf.transitions"

    def save(self, component: Any, path: Path, *, args: tuple, kwargs: Mapping[str, Any]) -> Any:
        """Writes the dataset to ``path / "transitions"`` (``args``, ``kwargs``: unused)."""
        component.dumps(path / "transitions")

    def load(self, component: Any, path: Path, **kwargs: Any) -> None:
        """Restores the dataset in place, checking env, reward and checksum.

        Args:
            component: the dataset.
            path: its folder.

        Keyword Args:
            **kwargs: torchrl's load options (unused).
        """
        component.loads(path / "transitions")


def _key_list(key: NestedKey) -> list[str]:
    return [key] if isinstance(key, str) else list(key)


class ReplayCheckpointAdapter(CheckpointAdapter):
    """Checkpoints a replay buffer's filled part only, with its write cursor.

    A ``LazyTensorStorage`` is allocated at full capacity (1e6 transitions for SAC), and the
    stock state dict writes all of it; this writes the ``len(buffer)`` filled rows as a
    memory-mapped TensorDict and restores them at the same positions, so sampling after a
    resume is identical. Loading reads the rows with
    :func:`~torchrl_mbmf.data.memmap.load_tensor_folder` (no pickle): only plain tensors of
    the recorded keys (and, when given, of ``keys``) are accepted.

    Args:
        keys: the keys the buffer may hold (e.g. the loss' ``in_keys``); the buffer's own
            ``"index"`` entry is always allowed. Defaults to the keys the checkpoint records.

    Examples:
        >>> import tempfile, torch
        >>> from pathlib import Path
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
        >>> from torchrl_mbmf.runs.storage import ReplayCheckpointAdapter
        >>> source = TensorDictReplayBuffer(storage=LazyTensorStorage(100))
        >>> _ = source.extend(TensorDict({"obs": torch.arange(7.0)}, [7]))
        >>> target = TensorDictReplayBuffer(storage=LazyTensorStorage(100))
        >>> with tempfile.TemporaryDirectory() as d:
        ...     ReplayCheckpointAdapter(keys=["obs"]).save(source, Path(d), args=(), kwargs={})
        ...     ReplayCheckpointAdapter(keys=["obs"]).load(target, Path(d))
        >>> len(target)
        7
    """

    adapter_id = "torchrl_mbmf.replay_filled"
    format_version = 2

    def __init__(self, keys: Collection[NestedKey] | None = None) -> None:
        self.keys = None if keys is None else {tuple(_key_list(k)) for k in keys} | {("index",)}

    def save(self, component: Any, path: Path, *, args: tuple, kwargs: Mapping[str, Any]) -> Any:
        """Writes the filled rows and the writer state below ``path``.

        Args:
            component: the replay buffer.
            path: its folder.

        Keyword Args:
            args: unused.
            kwargs: unused.
        """
        path.mkdir(parents=True, exist_ok=True)
        filled = len(component)
        keys: list[list[str]] = []
        if filled:
            rows = component.storage[:filled]
            keys = [_key_list(k) for k in rows.keys(True, True)]
            rows.memmap(path / "data")
        state = {"filled": filled, "keys": keys, "writer": component.writer.state_dict()}
        (path / "replay.json").write_text(json.dumps(state))

    def load(self, component: Any, path: Path, **kwargs: Any) -> None:
        """Restores the rows and the write cursor (no pickle).

        Args:
            component: the replay buffer.
            path: its folder.

        Keyword Args:
            **kwargs: torchrl's load options (unused).
        """
        record = path / "replay.json"
        try:
            state = json.loads(record.read_text())
            filled, keys = int(state["filled"]), [tuple(k) for k in state["keys"]]
            writer = state["writer"]
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise ValueError(f"replay checkpoint record {record} is unreadable: {err}") from err
        unexpected = [k for k in keys if self.keys is not None and k not in self.keys]
        if unexpected:
            raise ValueError(f"{record} lists unexpected keys {unexpected}")
        data = None
        if filled:
            try:
                data = load_tensor_folder(path / "data", keys=keys)
            except UnsafeFolderError as err:
                raise ValueError(f"replay checkpoint {path}: {err}") from err
            if data.batch_size[:1] != (filled,) or data.batch_dims != 1:
                raise ValueError(
                    f"replay checkpoint {path} holds {tuple(data.batch_size)} rows, "
                    f"its record says {filled}"
                )
            absent = [k for k in keys if k not in data.keys(True, True)]
            if absent:
                raise ValueError(f"replay checkpoint {path / 'data'} lacks the entries {absent}")
        component.empty()
        if data is not None:
            component.extend(data)
        component.writer.load_state_dict(writer)
