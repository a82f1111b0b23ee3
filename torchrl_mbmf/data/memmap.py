"""Reading memory-mapped TensorDict folders without unpickling anything.

``TensorDict.load_memmap`` restores non-tensor entries (``NonTensorData``, tensorclasses,
``other.pickle`` sidecars) with :mod:`pickle`, so loading a crafted folder can run arbitrary
code. :func:`load_tensor_folder` reads the same layout (written by ``TensorDict.memmap``) with
:mod:`json` and raw file reads only: every entry must be a plain dense tensor of an allowed
key, with a data file of exactly the size its dtype and shape give; anything else is refused
with an error naming the file.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Collection
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict
from tensordict.utils import NestedKey

__all__ = ["UnsafeFolderError", "is_stored_shape", "load_tensor_folder", "stored_dtype"]

_META = "meta.json"
_TD_TYPE = "<class 'tensordict._td.TensorDict'>"
_TENSOR_FIELDS = {"device", "shape", "dtype", "is_nested"}
_RESERVED = {"shape", "device", "_type"}
_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]*$")


class UnsafeFolderError(ValueError):
    """A memory-mapped folder holds a non-tensor, an unexpected key, or a bad tensor file."""


def _key_tuple(key: NestedKey) -> tuple[str, ...]:
    return (key,) if isinstance(key, str) else tuple(key)


def _read_meta(folder: Path) -> dict:
    meta_file = folder / _META
    if meta_file.is_symlink() or not meta_file.is_file():
        raise UnsafeFolderError(f"missing file {meta_file}")
    try:
        meta = json.loads(meta_file.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise UnsafeFolderError(f"{meta_file} is not valid JSON: {err}") from err
    if not isinstance(meta, dict) or meta.get("_type") != _TD_TYPE:
        found = meta.get("_type") if isinstance(meta, dict) else type(meta).__name__
        raise UnsafeFolderError(
            f"{meta_file} describes a {found!r}, expected a plain TensorDict ({_TD_TYPE!r})"
        )
    shape = meta.get("shape")
    if not is_stored_shape(shape):
        raise UnsafeFolderError(f"{meta_file} has an invalid batch shape {shape!r}")
    return meta


#: The dtypes a stored tensor may have: the plain numeric ones and ``bool``.
_STORED_DTYPES = {
    name: getattr(torch, name)
    for name in (
        "float16",
        "bfloat16",
        "float32",
        "float64",
        "uint8",
        "int8",
        "int16",
        "int32",
        "int64",
        "bool",
    )
}


def stored_dtype(name: object, *, prefix: str = "") -> torch.dtype | None:
    """The plain dtype that a stored file names as ``prefix + "<dtype>"``, else ``None``.

    Only the numeric dtypes and ``bool`` are allowed (nothing that needs code to rebuild).

    Args:
        name: the name read from the file (any JSON value).

    Keyword Args:
        prefix: the prefix the writer puts before the dtype's name (``"torch."`` in a
            ``TensorDict.memmap`` folder). Defaults to ``""``.

    Examples:
        >>> from torchrl_mbmf.data.memmap import stored_dtype
        >>> stored_dtype("torch.float32", prefix="torch."), stored_dtype("float32", prefix="torch.")
        (torch.float32, None)
        >>> stored_dtype("complex64") is None
        True
    """
    if not isinstance(name, str) or not name.startswith(prefix):
        return None
    return _STORED_DTYPES.get(name[len(prefix) :])


def is_stored_shape(value: object) -> bool:
    """Whether a value read from a stored file is a shape: a list of integers ``>= 0``.

    Args:
        value: the value (any JSON value).

    Examples:
        >>> from torchrl_mbmf.data.memmap import is_stored_shape
        >>> is_stored_shape([2, 3]), is_stored_shape([2, -1]), is_stored_shape([True])
        (True, False, False)
    """
    return isinstance(value, list) and all(
        isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in value
    )


def _read_tensor(file: Path, spec: dict, meta_file: Path, name: str) -> torch.Tensor:
    dtype = stored_dtype(spec.get("dtype"), prefix="torch.")
    shape = spec.get("shape")
    if dtype is None or spec.get("is_nested") is not False or not is_stored_shape(shape):
        raise UnsafeFolderError(
            f"{meta_file}: entry {name!r} is not a plain dense tensor "
            f"(dtype {spec.get('dtype')!r}, shape {shape!r}); refusing to load it"
        )
    if file.is_symlink() or not file.is_file():
        raise UnsafeFolderError(f"missing file {file} (entry {name!r} of {meta_file})")
    itemsize = torch.empty((), dtype=dtype).element_size()
    expected = int(np.prod(shape, dtype=np.int64)) * itemsize
    size = file.stat().st_size
    if size != expected:
        raise UnsafeFolderError(
            f"{file} has {size} bytes, expected {expected} for a {tuple(shape)} "
            f"{spec['dtype']} tensor (truncated or extended)"
        )
    raw = np.fromfile(file, dtype=np.uint8)
    return torch.from_numpy(raw).view(dtype).reshape(shape)


def _load(folder: Path, prefix: tuple[str, ...], allowed: set | None) -> TensorDict:
    meta = _read_meta(folder)
    meta_file = folder / _META
    expected_files = {_META}
    entries: dict[str, object] = {}
    for name, spec in meta.items():
        if name in _RESERVED:
            continue
        if not _NAME.match(name) or not isinstance(spec, dict):
            raise UnsafeFolderError(
                f"{meta_file}: entry {name!r} is not a plain tensor or TensorDict; "
                "refusing to load it"
            )
        key = (*prefix, name)
        if spec == {"type": "TensorDict"}:
            sub = folder / name
            if sub.is_symlink() or not sub.is_dir():
                raise UnsafeFolderError(f"missing folder {sub} (entry {name!r} of {meta_file})")
            expected_files.add(name)
            entries[name] = _load(sub, key, allowed)
        elif set(spec) == _TENSOR_FIELDS:
            if allowed is not None and key not in allowed:
                raise UnsafeFolderError(
                    f"{meta_file}: unexpected entry {key!r}; expected only {sorted(allowed)}"
                )
            expected_files.add(f"{name}.memmap")
            entries[name] = _read_tensor(folder / f"{name}.memmap", spec, meta_file, name)
        else:
            raise UnsafeFolderError(
                f"{meta_file}: entry {name!r} is not a plain tensor (found {spec!r}); "
                "refusing to load it"
            )
    for entry in os.scandir(folder):
        if entry.name not in expected_files:
            raise UnsafeFolderError(
                f"unexpected file {folder / entry.name} (not a tensor listed in {meta_file}); "
                "refusing to load the folder"
            )
    return TensorDict(entries, batch_size=meta["shape"])


def load_tensor_folder(
    path: str | os.PathLike, *, keys: Collection[NestedKey] | None = None
) -> TensorDict:
    """Loads a folder written by ``TensorDict.memmap`` holding plain tensors only.

    Nothing is unpickled and no file is memory-mapped: ``meta.json`` files are parsed as JSON
    and each tensor is read from its raw ``.memmap`` file, whose size must equal what its dtype
    and shape give. The result owns its memory (writing to it never touches the files).

    Args:
        path: the folder.

    Keyword Args:
        keys: the leaf keys the folder may hold (e.g. ``["state", ("next", "reward")]``).
            Defaults to any key.

    Returns:
        The TensorDict, with the saved batch size.

    Raises:
        UnsafeFolderError: on an entry that is not a plain dense tensor or TensorDict (a
            non-tensor, a tensorclass, a pickle sidecar), a key outside ``keys``, an
            unlisted file, or a missing, truncated or extended tensor file; the message
            names the file.

    Examples:
        >>> import tempfile, torch
        >>> from tensordict import TensorDict
        >>> from torchrl_mbmf.data.memmap import load_tensor_folder
        >>> td = TensorDict({"a": torch.arange(3.0), "next": {"b": torch.ones(3, 2)}}, [3])
        >>> with tempfile.TemporaryDirectory() as d:
        ...     _ = td.memmap(d)
        ...     loaded = load_tensor_folder(d, keys=["a", ("next", "b")])
        >>> loaded["next", "b"].shape, bool((loaded == td).all())
        (torch.Size([3, 2]), True)
    """
    folder = Path(path)
    if folder.is_symlink() or not folder.is_dir():
        raise UnsafeFolderError(f"missing folder {folder}")
    allowed = None if keys is None else {_key_tuple(k) for k in keys}
    return _load(folder, (), allowed)
