"""The public settings: the service's session-create schema (`public_model`: every setting but the
evaluation's ablations) and the CLI's ``--set PATH=VALUE`` (`parse_setting`, `settings_from_pairs`),
both read off the one definition in `settings`."""

from __future__ import annotations

from typing import Annotated, Any, get_args

from pydantic import BaseModel, ConfigDict, TypeAdapter, ValidationError, create_model

from .settings import SceneConfig, SettingsGroup, error_message

PRIVATE_GROUPS = ("research",)


def public_model(name: str = "SessionCreate", doc: str | None = None) -> type[BaseModel]:
    """A model of the settings a client may choose: every `SceneConfig` field (same types, bounds,
    defaults and docs) but the `PRIVATE_GROUPS`, closed to unknown names. Its validated dump
    (``exclude_unset=True``) is a valid `SceneConfig` keyword set."""
    fields = {k: (f.annotation, f) for k, f in SceneConfig.model_fields.items() if k not in PRIVATE_GROUPS}
    return create_model(name, __config__=ConfigDict(**{**SceneConfig.model_config, "frozen": False}),
                        __doc__=doc or SceneConfig.__doc__, **fields)


def _group_of(annotation: Any) -> type[SettingsGroup] | None:
    return annotation if isinstance(annotation, type) and issubclass(annotation, SettingsGroup) else None


def parse_setting(text: str) -> tuple[str, Any]:
    """``PATH=VALUE`` of a public setting -> (PATH, VALUE), VALUE read as the setting's type (numbers,
    ``true``/``false``, ``null`` for an optional setting, text for a choice) and checked against its
    bounds. Raises ValueError naming PATH for an unknown, private or invalid setting.

    Example:
        >>> parse_setting("free_space.margin=3"), parse_setting("colour_solve.views=16")
        (('free_space.margin', 3.0), ('colour_solve.views', 16))
    """
    path, sep, value = text.partition("=")
    path = path.strip()
    if not sep or not path:
        raise ValueError(f"setting: expected NAME=VALUE, got {text!r}")
    model: type[BaseModel] = SceneConfig
    parts = path.split(".")
    for depth, part in enumerate(parts):
        field = model.model_fields.get(part)
        if field is None or (depth == 0 and part in PRIVATE_GROUPS):
            raise ValueError(f"{path}: unknown setting")
        group = _group_of(field.annotation)
        if group is None:
            if depth != len(parts) - 1:
                raise ValueError(f"{path}: unknown setting ({'.'.join(parts[:depth + 1])} has no fields)")
            return path, _parse_value(path, field.annotation, field.metadata, value.strip())
        if depth == len(parts) - 1:
            raise ValueError(f"{path}: a group; set one of its fields, e.g. {path}.{next(iter(group.model_fields))}")
        model = group
    raise AssertionError("unreachable")


def _parse_value(path: str, annotation: Any, metadata: list, text: str) -> Any:
    optional = type(None) in get_args(annotation)
    if optional and text.lower() in ("null", "none"):
        return None
    base = next(a for a in get_args(annotation) if a is not type(None)) if optional else annotation
    try:
        adapter = TypeAdapter(Annotated[(base, *metadata)] if metadata else base, config=ConfigDict(allow_inf_nan=False))
        return adapter.validate_strings(text)
    except ValidationError as exc:
        raise ValueError(error_message(exc, path)) from None


def settings_from_pairs(pairs: list[tuple[str, Any]]) -> dict:
    """(path, value) pairs (`parse_setting`) -> the nested mapping `SceneConfig` and the service take."""
    out: dict[str, Any] = {}
    for path, value in pairs:
        *groups, name = path.split(".")
        target = out
        for g in groups:
            target = target.setdefault(g, {})
        target[name] = value
    return out
