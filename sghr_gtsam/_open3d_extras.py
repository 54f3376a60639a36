"""``import open3d`` without paying for its ``ml`` and ``visualization`` subpackages until they are used.

open3d's ``__init__`` imports both eagerly: ``open3d.ml`` pulls scikit-learn, ``open3d.visualization`` pulls
dash, plotly, pandas and IPython. That is ≈ 2.4 s of a 3.2 s import (quiet machine, measured with
``python -X importtime``), paid by every run and again by the executor's fork server, while this package
uses only open3d's geometry, pipelines, io and utility bindings.

``defer()`` puts a one-shot finder in front of ``import open3d``: just before open3d's ``__init__`` runs, the
two subpackages enter ``sys.modules`` as deferred modules (``_Deferred``), so its own
``import open3d.ml`` finds them there; afterwards they are set as attributes of the package as a normal
import would. The first attribute read of either (``open3d.visualization.draw_geometries``,
``import open3d.ml.torch``) runs its real code, so nothing is missing, only later.
"""

from __future__ import annotations

import importlib.abc
import importlib.machinery
import importlib.util
import sys
from types import ModuleType

DEFERRED = ("ml", "visualization")


def defer() -> None:
    """Install the finder, unless open3d is already imported (then there is nothing to defer)."""
    if "open3d" not in sys.modules and not any(isinstance(f, _Finder) for f in sys.meta_path):
        sys.meta_path.insert(0, _Finder())


class _Finder(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name != "open3d":
            return None
        sys.meta_path.remove(self)  # one shot: later imports take the ordinary path
        spec = importlib.machinery.PathFinder.find_spec(name, path)
        if spec is None or spec.loader is None or spec.submodule_search_locations is None:
            return spec
        spec.loader = _Loader(spec.loader)
        return spec


class _Loader(importlib.abc.Loader):
    def __init__(self, real: importlib.abc.Loader):
        self._real = real

    def create_module(self, spec):
        return self._real.create_module(spec)

    def exec_module(self, module: ModuleType) -> None:
        lazy = {}
        for sub in DEFERRED:
            name = f"{module.__name__}.{sub}"
            found = _deferred(name, module.__path__)
            if found is not None:
                lazy[sub] = sys.modules[name] = found
                # open3d's __init__ reads open3d.visualization in a Jupyter kernel (its web visualizer)
                setattr(module, sub, found)
        try:
            self._real.exec_module(module)
        except BaseException:
            for sub in lazy:
                sys.modules.pop(f"{module.__name__}.{sub}", None)
            raise
        module.__loader__ = module.__spec__.loader = self._real  # from here on an ordinary package


def _deferred(name: str, path: list[str]) -> ModuleType | None:
    spec = importlib.machinery.PathFinder.find_spec(name, path)
    if spec is None or spec.loader is None:
        return None
    module = importlib.util.module_from_spec(spec)
    module.__dict__.pop("__path__", None)  # importing a submodule reads it: that runs the package first
    module.__class__ = _Deferred
    return module


class _Deferred(ModuleType):
    """A module whose code has not run yet; the first read of a name it lacks (``__path__`` included) runs it.
    Unlike ``importlib.util.LazyLoader``, reading ``__spec__`` does not: the import system reads it when it
    finds the module in ``sys.modules``, as open3d's own ``import open3d.ml`` does."""

    def __getattr__(self, attr: str):
        spec = self.__spec__
        self.__class__ = ModuleType
        if spec.submodule_search_locations is not None:
            self.__path__ = spec.submodule_search_locations
        spec.loader.exec_module(self)
        return getattr(self, attr)
