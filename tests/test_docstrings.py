"""Every public name has a Google-style docstring whose Args match its signature."""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import pkgutil
import re

import pytest

import torchrl_mbmf

_SECTION = re.compile(r"^\s*(Args|Keyword Args|Returns|Raises|Examples|Yields|Attributes):\s*$")
_ARG = re.compile(r"^\s{4}(\*{0,2}\w+)(?: \(.*\))?:")


def _public_objects():
    seen = {}
    for info in pkgutil.walk_packages(torchrl_mbmf.__path__, prefix="torchrl_mbmf."):
        module = importlib.import_module(info.name)
        for name in getattr(module, "__all__", ()):
            obj = getattr(module, name)
            if inspect.isclass(obj) or inspect.isfunction(obj):
                seen[f"{obj.__module__}.{obj.__qualname__}"] = obj
    return sorted(seen.items())


def _documented_args(doc: str, sections=("Args", "Keyword Args")) -> set[str]:
    args, section = set(), None
    for line in doc.splitlines():
        m = _SECTION.match(line)
        if m:
            section = m.group(1)
            continue
        if section in sections:
            am = _ARG.match(line)
            if am:
                args.add(am.group(1).lstrip("*"))
    return args


PUBLIC = _public_objects()


def test_there_are_public_objects():
    assert len(PUBLIC) > 5


@pytest.mark.parametrize(("qualname", "obj"), PUBLIC, ids=[q for q, _ in PUBLIC])
def test_docstring_matches_signature(qualname, obj):
    doc = inspect.getdoc(obj)
    assert doc, f"{qualname} has no docstring"
    if inspect.isclass(obj) and issubclass(obj, BaseException):
        return
    assert "Examples:" in doc, f"{qualname} docstring has no Examples: section"
    func = obj.__init__ if inspect.isclass(obj) else obj
    if func is object.__init__:
        return
    params = {n for n, p in inspect.signature(func).parameters.items() if n not in ("self", "cls")}
    sections = ("Args", "Keyword Args")
    if dataclasses.is_dataclass(obj):
        sections = (*sections, "Attributes")
    documented = _documented_args(doc, sections)
    missing = params - documented
    extra = documented - params
    assert not missing, f"{qualname}: arguments not documented: {sorted(missing)}"
    assert not extra, f"{qualname}: documented arguments not in the signature: {sorted(extra)}"
