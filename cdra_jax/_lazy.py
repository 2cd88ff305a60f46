"""Names of a package that are imported on first use (PEP 562), so that importing the package,
or one of its lighter modules (the command line), does not load what it does not need
(matplotlib, scipy.stats and the like take a second on two cores)."""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping


def lazy_names(package: str, names: Mapping[str, str]) -> tuple[Callable, Callable]:
    """``(__getattr__, __dir__)`` for the module ``package``.

    Args:
        package: the package's ``__name__``.
        names: attribute name -> the submodule (relative, e.g. ``"calibrate"``) that defines
            it; a name that is itself a submodule maps to ``""``.

    The first access imports the submodule and keeps the value in the package's namespace (the
    next access is a plain attribute). Other names raise ``AttributeError`` as usual.
    """

    def __getattr__(name: str):
        if name not in names:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        where = names[name]
        module = importlib.import_module(f"{package}.{where or name}")
        value = module if not where else getattr(module, name)
        setattr(sys.modules[package], name, value)
        return value

    def __dir__() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | set(names))

    return __getattr__, __dir__
