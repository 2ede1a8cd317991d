"""The one way a stage package of the core names its public API: each name and the module that defines it, imported
when first asked for (``from lego_loam_py.core.mapping import MapOptimization``), so that a node loads only the
stages it uses."""

from __future__ import annotations

import importlib
from collections.abc import Callable

__all__ = ['lazy_exports']


def lazy_exports(package: str, exports: dict[str, str]) -> Callable[[str], object]:
    """A module ``__getattr__`` for ``package`` that imports ``exports[name]`` (a module of the package) on first
    use."""

    def __getattr__(name: str) -> object:
        module = exports.get(name)
        if module is None:
            raise AttributeError(f'module {package!r} has no attribute {name!r}')
        return getattr(importlib.import_module(f'{package}.{module}'), name)

    return __getattr__
