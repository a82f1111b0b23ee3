"""Import paths of names that moved: kept for one release, with a :class:`DeprecationWarning`."""

from __future__ import annotations

import importlib
import types
import warnings
from collections.abc import Mapping

__all__ = ["MovedModule", "moved_attribute", "warn_moved"]


def warn_moved(old: str, new: str, stacklevel: int = 3) -> None:
    """Warns that ``old`` moved to ``new`` and goes in the next release.

    Args:
        old: the old dotted path.
        new: the new dotted path.
        stacklevel: passed to :func:`warnings.warn`. Defaults to ``3`` (the line that used
            the old path, when called from a ``__getattr__``).

    Examples:
        >>> import warnings
        >>> from torchrl_mbmf.moved import warn_moved
        >>> with warnings.catch_warnings(record=True) as caught:
        ...     warnings.simplefilter("always")
        ...     warn_moved("a.old", "b.new")
        >>> str(caught[0].message)
        'a.old moved to b.new; the old path goes in the next release'
    """
    warnings.warn(
        f"{old} moved to {new}; the old path goes in the next release",
        DeprecationWarning,
        stacklevel=stacklevel,
    )


def moved_attribute(module: str, name: str, moved: Mapping[str, str]) -> object:
    """A module's ``__getattr__`` for names that left it: the name from its new module, warned.

    Args:
        module: the old module's name (its ``__name__``).
        name: the attribute asked for.
        moved: each moved name and the module that now holds it.

    Raises:
        AttributeError: ``name`` is not one of ``moved``.

    Examples:
        >>> import warnings
        >>> from torchrl_mbmf.moved import moved_attribute
        >>> with warnings.catch_warnings(record=True) as caught:
        ...     warnings.simplefilter("always")
        ...     f = moved_attribute("old", "check_number", {"check_number": "torchrl_mbmf.checks"})
        >>> f.__module__, str(caught[0].message).split(";")[0]
        ('torchrl_mbmf.checks', 'old.check_number moved to torchrl_mbmf.checks.check_number')
    """
    if name not in moved:
        raise AttributeError(f"module {module!r} has no attribute {name!r}")
    warn_moved(f"{module}.{name}", f"{moved[name]}.{name}", stacklevel=4)
    return getattr(importlib.import_module(moved[name]), name)


class MovedModule(types.ModuleType):
    """A former module: its names, read from their new modules, each with a warning.

    Put in :data:`sys.modules` under the old name, it keeps ``import old.module`` and
    ``from old.module import name`` working.

    Args:
        name: the former module's full name.
        targets: the modules that now hold its names, searched in order.

    Examples:
        >>> import warnings
        >>> from torchrl_mbmf.moved import MovedModule
        >>> old = MovedModule("pkg.guards", ("torchrl_mbmf.checks",))
        >>> with warnings.catch_warnings(record=True) as caught:
        ...     warnings.simplefilter("always")
        ...     old.check_finite.__module__
        'torchrl_mbmf.checks'
        >>> caught[0].category.__name__
        'DeprecationWarning'
    """

    def __init__(self, name: str, targets: tuple[str, ...]) -> None:
        super().__init__(name, f"Moved to {', '.join(targets)}.")
        self._targets = targets

    def __getattr__(self, name: str) -> object:
        if name.startswith("__") and name != "__all__":
            raise AttributeError(name)
        if name == "__all__":
            return [
                n for t in self._targets for n in getattr(importlib.import_module(t), "__all__", ())
            ]
        for target in self._targets:
            module = importlib.import_module(target)
            if hasattr(module, name):
                warn_moved(f"{self.__name__}.{name}", f"{target}.{name}")
                return getattr(module, name)
        raise AttributeError(f"module {self.__name__!r} has no attribute {name!r}")

    def __dir__(self) -> list[str]:
        return sorted({n for t in self._targets for n in dir(importlib.import_module(t))})
