"""Plug-in laws: ``package.module:ClassName`` to a class, with one-line errors.

Input: an import path ``package.module:ClassName`` (``guidance.law``,
``control.law``) and the base class the plug-in must subclass
(:class:`gnc.guidance.GuidanceLaw`, :class:`gnc.control.Controller`).
Output: the class. Called at scenario validation (so a bad plug-in is refused
before anything runs or is written) and when the flight software is built.

In flight, :func:`check_law_vector` checks what a law or controller returns at
every control tick: a non-finite or misshapen command raises
:class:`LawOutputError` naming the law, the value, the time and what is allowed,
so that a broken law ends the run instead of being flown silently (the
controller would otherwise hold its last good command, or clamp a NaN thrust
to the engine's minimum); a plug-in that raises in flight gets the same one
line (:func:`plugin_raised`), with its exception and the line that raised.

The module is imported with the current working directory on the search path
(so ``my_law.py`` beside the scenario works from that folder), and is refused
if its source imports the simulator or the truth side (``mujoco``,
``models``, ``bench``): a plug-in is flight software and sees only what the
flight software gives it (the navigation state, the target, the commands).
"""

from __future__ import annotations

import ast
import importlib
import inspect
import os
import re
import sys
import traceback
from pathlib import Path

import numpy as np

# Roots a flight-software module may not import (as tests/test_boundary.py enforces for gnc/ and vision/).
FORBIDDEN_ROOTS = frozenset({"mujoco", "models", "bench", "dm_control"})
_SPEC = re.compile(r"^[A-Za-z_]\w*(\.[A-Za-z_]\w*)*:[A-Za-z_]\w*$")


class LawOutputError(ValueError):
    """A guidance law or controller returned a command the vehicle cannot fly (non-finite, wrong shape).

    A ValueError: a user's plug-in is the usual cause, so the command line shows it as one
    ``landbench: error:`` line and a campaign records the case as an error row with the message.
    """


def check_law_vector(value: object, size: int, field: str, law: str, what: str, t_ns: int, unit: str) -> None:
    """Raise :class:`LawOutputError` unless ``value`` is a finite vector of ``size`` numbers.

    Args:
        value: What the law returned (a NumPy array, a sequence or a float; a float for ``size`` 0).
        size: Expected number of elements; 0 for a scalar.
        field: Scenario field of the law (``guidance.law``, ``control.law``).
        law: Its value (``apollo``, ``my_law:MyLaw``).
        what: What was returned, e.g. ``"accel_L (the approach acceleration)"``.
        t_ns: Time of the control tick [ns].
        unit: Unit of the value, for the message, e.g. ``"m/s^2"``.
    """
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        arr = None
    shape = () if size == 0 else (size,)
    if arr is not None and arr.shape == shape and np.isfinite(arr).all():
        return
    want = "a finite number" if size == 0 else f"a finite vector of {size} numbers, shape ({size},)"
    if arr is not None and arr.size <= 64:  # on one line whatever the shape
        shown = np.array2string(arr.ravel() if arr.ndim > 1 else arr, precision=4, separator=", ", threshold=12)
    else:
        shown = repr(value)[:80]
    got = f"shape {arr.shape} " if arr is not None and arr.shape != shape else ""
    raise LawOutputError(f"{field} = {law!r}: {what} returned {got}{shown} at t = {t_ns / 1e9:.3f} s; allowed: "
                         f"{want} [{unit}] (README: Controller design studies)")


def plugin_raised(field: str, law: str, what: str, t_ns: int | None, exc: BaseException) -> LawOutputError:
    """The one-line error for a plug-in that raised in flight: its exception and the plug-in's line that raised.

    Args:
        field: Scenario field of the law (``guidance.law``, ``control.law``).
        law: Its value, an import path ``package.module:ClassName``.
        what: The method that raised, e.g. ``"update"``.
        t_ns: Time of the control tick [ns] (None: before the flight, when the plug-in is built).
        exc: The exception.
    """
    frames = traceback.extract_tb(exc.__traceback__)
    where = f" ({Path(frames[-1].filename).name}:{frames[-1].lineno})" if frames else ""
    text = " ".join(str(exc).split())  # one line
    when = "" if t_ns is None else f" at t = {t_ns / 1e9:.3f} s"
    return LawOutputError(f"{field} = {law!r}: {what} raised {type(exc).__name__}: {text}{where}{when}")


def call_law(law: str, field: str, what: str, t_ns: int | None, keep: type[BaseException], fn, *args: object):
    """``fn(*args)`` for the law ``law``: a plug-in's exception becomes one line (:func:`plugin_raised`), chained.

    An exception of type ``keep`` passes as it is (it names its field already), and so does any exception
    of a built-in law (a defect of this software, with its traceback).
    """
    if not is_plugin(law):
        return fn(*args)
    try:
        return fn(*args)
    except keep:
        raise
    except Exception as exc:  # noqa: BLE001 - any error in the user's plug-in is one line, chained
        raise plugin_raised(field, law, what, t_ns, exc) from exc


def build_law(cls: type, law: str, field: str, *args: object) -> object:
    """``cls(*args)``; a plug-in whose constructor raises gets one line (:func:`call_law`); a ValueError passes
    as it is (the options' validation names its field already)."""
    return call_law(law, field, "__init__", None, ValueError, cls, *args)


def is_plugin(law: str) -> bool:
    """Whether a law value is a user's plug-in (an import path) rather than a built-in name."""
    return ":" in law


def _boundary_violations(module) -> set[str]:
    """Forbidden roots the module's own source imports (empty when it has no readable source)."""
    path = getattr(module, "__file__", None)
    if not path or not str(path).endswith(".py"):
        return set()
    try:
        tree = ast.parse(Path(path).read_text(encoding="utf-8"))
    except (OSError, SyntaxError, UnicodeDecodeError):
        return set()
    roots: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            roots |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            roots.add(node.module.split(".")[0])
    return roots & FORBIDDEN_ROOTS


def load_law_class(spec: str, base: type, shown: str | None = None, field: str = "guidance.law",
                   what: str = "guidance law") -> type:
    """Import ``package.module:ClassName`` and check it implements ``base``'s interface.

    Args:
        spec: The import path.
        base: The abstract base class the plug-in must subclass.
        shown: The value to name in messages (default ``spec``).
        field: The scenario field named in messages (``guidance.law``, ``control.law``).
        what: What the class is, in messages ("guidance law", "controller").

    Returns:
        The class.

    Raises:
        ValueError: One line: malformed path, module that does not import,
            missing class, not a subclass of ``base``, abstract methods left
            unimplemented, or a module that imports the simulator/truth side.
    """
    shown = spec if shown is None else shown
    head = f"{field} = {shown!r}"
    if not _SPEC.match(spec):
        raise ValueError(f"{head}: not an import path; allowed: a built-in law name or 'package.module:ClassName'")
    module_name, class_name = spec.split(":")
    cwd = os.getcwd()
    if cwd not in sys.path and "" not in sys.path:
        sys.path.append(cwd)  # plug-ins beside the scenario; kept for spawned campaign workers
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        missing = exc.name or module_name
        if missing == module_name or module_name.startswith(f"{missing}."):
            raise ValueError(f"{head}: no module named {module_name!r} on the Python path; allowed: an importable "
                             f"module (installed, on PYTHONPATH, or a .py file in the current folder {cwd})") from None
        raise ValueError(f"{head}: importing {module_name!r} failed: it needs the module {missing!r}, "
                         "which is not installed") from None
    except Exception as exc:  # noqa: BLE001 - any error in the user's module is one line, not a traceback
        raise ValueError(f"{head}: importing {module_name!r} failed: {type(exc).__name__}: {exc}") from None
    bad = _boundary_violations(module)
    if bad:
        raise ValueError(f"{head}: module {module_name!r} imports {', '.join(sorted(bad))}; a {what} is flight "
                         "software and may not import the simulator or the truth side (use gnc, numpy, scipy, ...)")
    cls = getattr(module, class_name, None)
    if cls is None:
        names = sorted(n for n, v in vars(module).items()
                       if inspect.isclass(v) and issubclass(v, base) and not inspect.isabstract(v)
                       and v.__module__ == module.__name__)
        hint = f"; classes there implementing the interface: {', '.join(names)}" if names else ""
        raise ValueError(f"{head}: module {module_name!r} has no class {class_name!r}{hint}")
    if not (inspect.isclass(cls) and issubclass(cls, base)):
        raise ValueError(f"{head}: {class_name!r} does not implement the {what} interface; allowed: a subclass of "
                         f"{base.__module__}.{base.__name__} (README: Controller design studies)")
    if inspect.isabstract(cls):
        missing = ", ".join(sorted(cls.__abstractmethods__))
        raise ValueError(f"{head}: {class_name!r} lacks the interface's methods {missing}; allowed: a class that "
                         "implements them (README: Controller design studies)")
    options = getattr(cls, "Options", None)
    from pydantic import BaseModel

    if options is not None and not (inspect.isclass(options) and issubclass(options, BaseModel)):
        raise ValueError(f"{head}: {class_name}.Options = {options!r}; allowed: a pydantic BaseModel subclass, or None")
    return cls
