"""Validated configs with one-line errors (shared by flight software and the bench).

A user's mistake in any pydantic config (``extra="forbid"``) must read as one
line naming the field, the bad value and what is allowed. Lives in ``gnc/``
because flight software may not import ``bench/``, while ``bench/`` may
import ``gnc/``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from pydantic import BaseModel, ValidationError


def _allowed_fields(model: type[BaseModel], loc: tuple[str, ...]) -> str:
    """Field names allowed at the parent of ``loc`` (for unknown-key errors)."""
    sub: Any = model
    for part in loc[:-1]:
        field = getattr(sub, "model_fields", {}).get(part)
        ann = field.annotation if field is not None else None
        if not (isinstance(ann, type) and issubclass(ann, BaseModel)):
            return ""
        sub = ann
    return ", ".join(sub.model_fields)


def format_validation_error(err: ValidationError, model: type[BaseModel], prefix: str = "") -> str:
    """Turn pydantic's multi-line report into one line: field, bad value, what is allowed.

    Args:
        err: The validation error.
        model: The model that was validated (to list allowed fields).
        prefix: Dotted name of the config in messages (e.g. ``"guidance"``), or "".

    Returns:
        One line, e.g. ``lander.dry_mass_kg = -5: Input should be greater than 0``.
    """
    errors = err.errors(include_url=False)
    first = errors[0]
    loc = tuple(str(p) for p in first.get("loc", ()))
    path = ".".join((prefix, *loc) if prefix else loc)
    msg = str(first.get("msg", "invalid")).removeprefix("Value error, ")
    if first.get("type") == "extra_forbidden":
        allowed = _allowed_fields(model, loc)
        line = f"unknown field '{path}'" + (f"; allowed here: {allowed}" if allowed else "")
    elif loc and msg.startswith(path):  # a validator that names its own field (and sub-field) already
        line = msg
    elif loc:
        line = f"{path} = {first.get('input')!r}: {msg}"
    else:
        line = f"{prefix}: {msg}" if prefix else msg  # model-level validators name their own fields
    if len(errors) > 1:
        line += f" (and {len(errors) - 1} more error{'s' if len(errors) > 2 else ''})"
    return line.replace("\n", " ")


def validated_config(model: type[BaseModel], cfg: BaseModel | Mapping[str, Any] | None, prefix: str) -> Any:
    """Validate a config given as a model, a mapping or None (defaults).

    Args:
        model: The pydantic model class.
        cfg: An instance of ``model``, a mapping of its fields, or None.
        prefix: Name of the config in messages, e.g. ``"guidance"``.

    Returns:
        A validated ``model`` instance.

    Raises:
        ValueError: One line naming the field, the bad value and what is allowed.
    """
    if cfg is None:
        return model()
    if isinstance(cfg, model):
        data: Any = cfg.model_dump()  # re-validate: model_construct or assignment may have bypassed checks
    elif isinstance(cfg, Mapping):
        data = dict(cfg)
    else:
        raise ValueError(f"{prefix} = {cfg!r}: expected a {model.__name__} or a mapping of its fields")
    try:
        return model.model_validate(data)
    except ValidationError as err:
        raise ValueError(format_validation_error(err, model, prefix)) from None


def validate_options(cls: type, law: str, options: Mapping[str, Any] | None, field: str,
                     what: str) -> BaseModel | None:
    """Validate a law's free-form options table (``field``, e.g. ``"guidance.options"``) with its ``Options`` model.

    Returns the validated options, or None when ``cls`` declares no ``Options`` (then the table
    must be empty). Raises a one-line ValueError naming ``<field>.<name>``, the bad value and what
    is allowed; ``what`` names the kind of plug-in in it (``"law"``, ``"controller"``).
    """
    options = dict(options or {})
    model = getattr(cls, "Options", None)
    if model is None:
        if options:
            raise ValueError(f"{field} = {options!r}: {what} {law!r} takes no options; allowed: an empty table")
        return None
    try:
        return model.model_validate(options)
    except ValidationError as err:
        raise ValueError(f"{format_validation_error(err, model, field)} (options of {what} {law!r})") from None
