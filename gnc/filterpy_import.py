"""filterpy's Kalman filters, imported without the filterpy subpackages the filters never call.

``import filterpy.kalman`` runs filterpy's package ``__init__``, which imports every subpackage.
Two of them import SciPy modules that nothing in landbench's flight software uses:
``filterpy.stats`` (``scipy.stats``: its distributions are built at import, about 0.5 s; the
filters call only its ``logpdf``, and only for a log-likelihood on request) and
``filterpy.discrete_bayes`` (``scipy.ndimage``, about 0.15 s). Together that is about 5 % of a
default ``landbench run``, paid again by every process that imports the filter.

:func:`defer_unused_subpackages`, called before filterpy is first imported, puts a stand-in for
each of the two in ``sys.modules``. A stand-in imports the real subpackage the first time anything
is read from it (PEP 562's module ``__getattr__``) and passes the read on, so ``filterpy.stats``
works as before for whoever uses it, only later. ``logpdf``, which the filter modules bind at
their import, is a function that does the same when it is called. Once filterpy has been imported
(by this module or by anyone else) nothing is changed.
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import sys
import types
from typing import Any

# filterpy subpackage -> the names other filterpy modules import from it while filterpy is imported.
DEFERRED: dict[str, tuple[str, ...]] = {"filterpy.stats": ("logpdf",), "filterpy.discrete_bayes": ()}


class _Deferred(types.ModuleType):
    """Stands in ``sys.modules`` for a filterpy subpackage until something is read from it."""

    def __getattr__(self, name: str) -> Any:
        return getattr(load(self.__name__), name)


def load(name: str) -> types.ModuleType:
    """The real subpackage ``name`` (imported now if only its stand-in is there)."""
    module = sys.modules.get(name)
    if isinstance(module, _Deferred):
        del sys.modules[name]
        try:
            return importlib.import_module(name)  # it also rebinds the parent package's attribute to it
        except BaseException:
            sys.modules.setdefault(name, module)  # the stand-in stays: the next use tries again
            raise
    return module if module is not None else importlib.import_module(name)


def _forwarder(module: str, attr: str):
    def forward(*args: Any, **kwargs: Any) -> Any:
        return getattr(load(module), attr)(*args, **kwargs)

    forward.__name__ = forward.__qualname__ = attr
    forward.__doc__ = f"``{module}.{attr}``, imported at the first call."
    return forward


def _stand_in(name: str) -> _Deferred:
    module = _Deferred(name, f"Stand-in for {name}, imported when first used (gnc.filterpy_import).")
    # The real package's folders: ``from filterpy.stats import logpdf`` reads ``__path__`` (a package?) without
    # meaning to load it, and ``import filterpy.stats.stats`` finds the submodule through it.
    parent, _, child = name.rpartition(".")
    module.__path__ = [os.path.join(p, child) for p in importlib.util.find_spec(parent).submodule_search_locations]
    for attr in DEFERRED[name]:
        setattr(module, attr, _forwarder(name, attr))
    return module


def defer_unused_subpackages() -> None:
    """Put the stand-ins in ``sys.modules`` if filterpy has not been imported yet (else do nothing)."""
    if "filterpy" in sys.modules:
        return
    for name in DEFERRED:
        sys.modules.setdefault(name, _stand_in(name))


defer_unused_subpackages()

from filterpy.kalman import ExtendedKalmanFilter  # noqa: E402 - after the stand-ins, on purpose

__all__ = ["ExtendedKalmanFilter", "defer_unused_subpackages", "load"]
