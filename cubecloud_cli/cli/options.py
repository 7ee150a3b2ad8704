"""Command-line options made from settings fields, as nerfstudio makes them from config fields.

A settings field's docstring is the option's help, and the help ends with the presets' values
of the field (presets.py) or the field's default: nothing about an option is typed twice. Every
option of a settings field defaults to None, "unset": the preset's value applies, else the
field's default (presets.resolve).
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import inspect
import textwrap
from typing import Any, Mapping, TypeVar

import typer

from cubecloud_cli.presets import is_preset_key, preset_note, resolve, shown

S = TypeVar("S")


@functools.cache
def field_docs(settings_class: type) -> dict[str, str]:
    """The docstring under each field of a dataclass, joined into one line."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(settings_class)))
    body = tree.body[0].body  # type: ignore[attr-defined]
    docs = {}
    for statement, following in zip(body, body[1:]):
        if (
            isinstance(statement, ast.AnnAssign)
            and isinstance(statement.target, ast.Name)
            and isinstance(following, ast.Expr)
            and isinstance(following.value, ast.Constant)
            and isinstance(following.value.value, str)
        ):
            docs[statement.target.id] = " ".join(inspect.cleandoc(following.value.value).split())
    return docs


def default_note(settings_class: type, name: str) -> str:
    """ "(preset: ...)" for a field the presets set, "(default: ...)" otherwise, "" for a None default
    (the docstring says what leaving it out means)."""
    stage = getattr(settings_class, "STAGE", None)
    if stage is not None and is_preset_key(stage, name):
        return preset_note(stage, name)
    field = next(f for f in dataclasses.fields(settings_class) if f.name == name)
    if field.default is None or field.default is dataclasses.MISSING:
        return ""
    return f"(default: {shown(name, field.default)})"


def field_help(settings_class: type, name: str, extra: str = "") -> str:
    docs = field_docs(settings_class)
    if name not in docs:
        raise KeyError(f"{settings_class.__name__}.{name} has no docstring to serve as its help")
    return " ".join(part for part in (docs[name], extra, default_note(settings_class, name)) if part)


def settings_option(settings_class: type, name: str, *flags: str, extra: str = "") -> Any:
    """The typer option of one settings field: ``--field-name`` unless ``flags`` are given."""
    declared = flags or ("--" + name.replace("_", "-"),)
    return typer.Option(*declared, help=field_help(settings_class, name, extra), show_default=False)


def build_settings(settings_class: type[S], preset: str | None, options: Mapping[str, Any]) -> S:
    """Settings whose options given win, then the preset's values, then the fields' defaults."""
    stage = getattr(settings_class, "STAGE", None)
    if stage is None or preset is None:
        return settings_class(**{key: value for key, value in options.items() if value is not None})
    return settings_class(**resolve(stage, preset, options))
