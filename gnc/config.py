"""Validated configs with one-line errors (shared by flight software and the bench).

A user's mistake in any pydantic config (``extra="forbid"``) must read as one
line naming the field, the bad value and what is allowed. Lives in ``gnc/``
because flight software may not import ``bench/``, while ``bench/`` may
import ``gnc/``.
"""

from __future__ import annotations

import re
import types
import typing
from collections.abc import Mapping
from typing import Any

from pydantic import BaseModel, ValidationError


def _tagged_models(ann: Any) -> dict[str, type[BaseModel]]:
    """The models of a discriminated union (``Annotated[Union[...], Field(discriminator=...)]``), by tag value
    (empty: not such a union)."""
    if typing.get_origin(ann) is not typing.Annotated:
        return {}
    key = next((m.discriminator for m in typing.get_args(ann)[1:] if isinstance(getattr(m, "discriminator", None), str)),
               None)
    out: dict[str, type[BaseModel]] = {}
    for t in _leaf_types(ann) if key else ():
        field = t.model_fields.get(key) if isinstance(t, type) and issubclass(t, BaseModel) else None
        for tag in typing.get_args(field.annotation) if field is not None else ():
            out.setdefault(str(tag), t)
    return out


def _resolve(model: type[BaseModel], loc: tuple[str, ...]) -> tuple[tuple[str, ...], Any, Any, Any]:
    """``loc`` without the tags pydantic puts in the path of a tagged union's member (``faults.0.dropout.t_s``
    is the user's ``faults.0.t_s``), the annotation of the field it ends at (None: not found), the model
    whose field that is (or where the path left the models: an unknown field's table) and the model the
    path ends at (a table's, else None)."""
    out: list[str] = []
    sub: Any = model
    ann: Any = None
    i = 0
    while i < len(loc):
        part = loc[i]
        field = getattr(sub, "model_fields", {}).get(part) if isinstance(sub, type) else None
        if field is None:
            return (*out, *loc[i:]), None, sub, None
        owner = sub
        out.append(part)
        ann = field.annotation
        if typing.get_origin(ann) in (list, tuple) and i + 1 < len(loc) and loc[i + 1].isdigit():
            i += 1
            out.append(loc[i])
            ann = typing.get_args(ann)[0] if typing.get_args(ann) else None
        elif typing.get_origin(ann) is dict and i + 1 < len(loc) and len(typing.get_args(ann)) == 2:
            i += 1  # a key of a table of tables (``dispersions``)
            out.append(loc[i])
            ann = typing.get_args(ann)[1]
        tagged = _tagged_models(ann)
        if tagged and i + 1 < len(loc) and loc[i + 1] in tagged:
            i += 1  # the tag: not a field the user wrote
            sub = tagged[loc[i]]
        else:
            models = [t for t in _leaf_types(ann) if isinstance(t, type) and issubclass(t, BaseModel)]
            sub = models[0] if len(models) == 1 else None
        i += 1
    return tuple(out), ann, owner if loc else model, sub


def _literal_values(ann: Any) -> list[str]:
    """The values a Literal annotation (or an Optional one) admits (empty: not a Literal)."""
    return [str(v) for t in _leaf_types(ann) if typing.get_origin(t) is typing.Literal for v in typing.get_args(t)]


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
    loc, ann, owner, table = _resolve(model, tuple(str(p) for p in first.get("loc", ())))
    path = ".".join((prefix, *loc) if prefix else loc)
    msg = str(first.get("msg", "invalid")).removeprefix("Value error, ")
    kind = first.get("type")
    if kind == "missing" and loc:  # the table quoted whole said only "Field required"
        allowed = _literal_values(ann)
        line = f"{path} is missing" + (f"; allowed: {', '.join(allowed)}" if allowed else "; give a value")
    elif kind == "union_tag_not_found" and loc:
        tag = str((first.get("ctx") or {}).get("discriminator", "kind")).strip("'")
        tags = list(_tagged_models(ann))  # the union the path ends at
        line = f"{path}.{tag} is missing" + (f"; allowed: {', '.join(tags)}" if tags else "")
    elif kind == "extra_forbidden":
        allowed = ", ".join(getattr(owner, "model_fields", None) or ())  # the table the unknown key is in
        line = f"unknown field '{path}'" + (f"; allowed here: {allowed}" if allowed else "")
    elif loc and msg.startswith(path):  # a validator that names its own field (and sub-field) already
        line = msg
    elif loc and first.get("type") == "value_error" and isinstance(first.get("input"), dict):
        # A table's own validator names the table's fields: the table itself is not quoted, and a field named
        # from the table down (``rcs.min_on_ns`` in ``lander.rcs``) gets the rest of its path.
        parent, _, last = path.rpartition(".")
        head = re.match(r"\w+", msg)
        if parent and msg.startswith(f"{last}."):
            line = f"{parent}.{msg}"
        elif head and head.group() in (getattr(table, "model_fields", None) or ()):  # one of the table's own fields
            line = f"{path}.{msg}"
        else:
            line = f"{path}: {msg}"
    elif loc:
        value = first.get("input")
        line = f"{path} = {_as_written(value)}: {msg}"
        if kind == "literal_error" and isinstance(value, bool):  # nav_map = true: a switch is a word
            line += f"; allowed: {' or '.join(map(repr, _literal_values(ann)))}, in quotes (a word, not a boolean)"
    else:
        line = f"{prefix}: {msg}" if prefix else msg  # model-level validators name their own fields
    if len(errors) > 1:
        line += f" (and {len(errors) - 1} more error{'s' if len(errors) > 2 else ''})"
    return line.replace("\n", " ")


def _as_written(value: Any) -> str:
    """A bad value as the user wrote it in TOML or ``--set``: ``true``/``false`` for booleans, else its repr."""
    if isinstance(value, bool):
        return "true" if value else "false"
    return repr(value)


def _leaf_types(ann: Any) -> list[Any]:
    """The types an annotation admits: Optional/Union/Annotated unwrapped, containers kept whole."""
    origin = typing.get_origin(ann)
    if origin is typing.Annotated:
        return _leaf_types(typing.get_args(ann)[0])
    if origin is typing.Union or origin is types.UnionType:
        return [t for a in typing.get_args(ann) for t in _leaf_types(a)]
    return [ann]


def _bool_in(ann: Any, value: Any, path: str) -> tuple[str, bool | str] | None:
    """(dotted path, value) of a boolean, or a string, given where ``ann`` wants a number (and no boolean, or
    no string), else None."""
    leaves = _leaf_types(ann)
    if isinstance(value, (bool, str)):
        numeric = any(t in (int, float) for t in leaves) and Any not in leaves
        if isinstance(value, bool):
            return (path, value) if numeric and bool not in leaves else None
        wants_text = str in leaves or any(typing.get_origin(t) is typing.Literal for t in leaves)
        try:  # only a string that reads as a number is taken silently; pydantic names any other
            float(value)
        except ValueError:
            return None
        return (path, value) if numeric and not wants_text else None
    if isinstance(value, Mapping):  # a model, or one of a union of models told apart by Literal fields ("kind")
        for t in leaves:
            if isinstance(t, type) and issubclass(t, BaseModel) and _literals_match(t, value):
                return _bool_in_model(t, value, path)
        return None
    if isinstance(value, (list, tuple)):
        for t in leaves:
            origin, args = typing.get_origin(t), typing.get_args(t)
            if origin in (list, tuple) and args:
                items = args if origin is tuple and Ellipsis not in args and len(args) == len(value) else None
                for k, v in enumerate(value):
                    # A table in an array is named as pydantic names it (faults.0.t_s); a number by its index.
                    sub = f"{path}.{k}" if isinstance(v, Mapping) else f"{path}[{k}]"
                    if hit := _bool_in(items[k] if items else args[0], v, sub):
                        return hit
                return None
    return None


def _literals_match(model: type[BaseModel], data: Mapping[str, Any]) -> bool:
    """Whether ``data``'s values for ``model``'s Literal fields are among their allowed values."""
    for name, field in model.model_fields.items():
        key = field.alias or name
        if typing.get_origin(field.annotation) is typing.Literal and key in data \
                and data[key] not in typing.get_args(field.annotation):
            return False
    return True


def _bool_in_model(model: type[BaseModel], data: Mapping[str, Any], prefix: str) -> tuple[str, bool] | None:
    for name, field in model.model_fields.items():
        key = field.alias or name
        if key in data and (hit := _bool_in(field.annotation, data[key], f"{prefix}.{key}" if prefix else key)):
            return hit
    return None


def bool_for_number(model: type[BaseModel], data: Any, prefix: str = "") -> str | None:
    """Find a boolean, or a string, given for a numeric field (pydantic's lax mode reads ``true`` as 1 and
    ``"5"`` as 5).

    Args:
        model: The model ``data`` is for.
        data: Its raw input (a mapping, as parsed from TOML or ``--set``).
        prefix: Dotted name of the config in messages, or "".

    Returns:
        None, or one line naming the field and the value: ``sim.t_max_ns = true: a number is expected,
        not a boolean; ...``.
    """
    hit = _bool_in_model(model, data, prefix) if isinstance(data, Mapping) else None
    if hit is None:
        return None
    path, value = hit
    if isinstance(value, str):  # pydantic's lax mode read "5" as 5 and "1e3" as 1000
        return (f"{path} = {_as_written(value)}: a number is expected, not a string; allowed: a number, written "
                "without quotes")
    return (f"{path} = {_as_written(value)}: a number is expected, not a boolean; allowed: a number "
            "(write 1 or 0 if that is what you meant)")


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
    if (line := bool_for_number(model, data, prefix)) is not None:
        raise ValueError(line)
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
    if (line := bool_for_number(model, options, field)) is not None:
        raise ValueError(f"{line} (options of {what} {law!r})")
    try:
        return model.model_validate(options)
    except ValidationError as err:
        raise ValueError(f"{format_validation_error(err, model, field)} (options of {what} {law!r})") from None
