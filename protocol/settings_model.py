"""What every process's settings model shares (torch-free): environment names, command-line flags generated from
the model's fields, errors that name the flag or the variable, and a Markdown table of the settings."""

from __future__ import annotations

import argparse
from typing import Any, Literal, get_args, get_origin

from pydantic import BaseModel, ValidationError
from pydantic_settings import BaseSettings


def env_name(model: type[BaseModel], name: str) -> str:
    """The environment variable of field `name`: its alias, else the model's prefix + the name in capitals."""
    alias = model.model_fields[name].validation_alias
    return alias if isinstance(alias, str) else str(model.model_config.get("env_prefix", "")) + name.upper()


def flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def _choices(annotation: Any) -> tuple[str, ...]:
    return tuple(get_args(annotation)) if get_origin(annotation) is Literal else ()


def default_text(model: type[BaseModel], name: str) -> str:
    default = model.model_fields[name].get_default(call_default_factory=True)
    return '""' if default == "" else "none" if default is None or default in ({}, frozenset()) else str(default)


def option_parser(model: type[BaseModel], **kwargs: Any) -> argparse.ArgumentParser:
    """An argparse parser with one option per field of `model`; only the options given end up in its namespace."""
    parser = argparse.ArgumentParser(argument_default=argparse.SUPPRESS, **kwargs)
    for name, field in model.model_fields.items():
        choices = _choices(field.annotation)
        metavar = "{" + ",".join(choices) + "}" if choices else getattr(field.annotation, "__name__", "VALUE").upper()
        help_text = f"{field.description} [{env_name(model, name)}; default: {default_text(model, name)}]"
        parser.add_argument(flag(name), dest=name, metavar=metavar, help=help_text.replace("%", "%%"))
    return parser


def explain(err: ValidationError, model: type[BaseModel], given: set[str] = frozenset()) -> str:  # type: ignore[assignment]
    """One line per error, naming the flag (for values given on the command line) or the environment variable."""
    by_key = {**{name: name for name in model.model_fields}, **{env_name(model, name): name
                                                                 for name in model.model_fields}}
    lines = []
    for error in err.errors():
        key = str(error["loc"][0]) if error["loc"] else ""
        name = by_key.get(key, key)
        where = flag(name) if name in given else env_name(model, name) if name in model.model_fields else key
        message = str(error["ctx"]["error"]) if error["type"] == "value_error" else error["msg"]
        lines.append(f"{where}: {message} (got {error.get('input')!r})")
    return "; ".join(lines)


def parse_settings(model: type[BaseSettings], argv: list[str] | None,
                   parser: argparse.ArgumentParser | None = None) -> Any:
    """`model` from the command line over the environment over its defaults; a bad value exits 2 naming it."""
    parser = parser or option_parser(model)
    given = vars(parser.parse_args(argv))
    try:
        return model(**given)
    except ValidationError as err:
        parser.error(explain(err, model, set(given)))


def markdown_table(model: type[BaseModel], flags: bool = True) -> str:
    """The settings of `model` as a Markdown table (README)."""
    head = "| Environment | Flag | Default | Meaning |\n|---|---|---|---|" if flags else \
        "| Environment | Default | Meaning |\n|---|---|---|"
    rows = []
    for name, field in model.model_fields.items():
        cells = [f"`{env_name(model, name)}`"] + ([f"`{flag(name)}`"] if flags else []) + \
                [f"`{default_text(model, name)}`", (field.description or "").replace("|", "\\|")]
        rows.append("| " + " | ".join(cells) + " |")
    return "\n".join([head, *rows])
