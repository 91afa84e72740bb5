"""Where engine parameters come from besides code: a config file (TOML, YAML or JSON) and the
``TOPOFUSION_ENGINE__*`` variables, read into nested mappings and merged.

The engine's configuration (:mod:`service.config`) and the settings root
(:mod:`service.settings`) both read them; neither is needed to read them.
"""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

#: Environment variables of single engine parameters start with this (then ``SECTION__FIELD``).
ENV_PREFIX = "TOPOFUSION_ENGINE__"


class ConfigError(ValueError):
    """A configuration that cannot be used; the message names the key."""


# -- reading a config file and the engine's variables ---------------------------------------------


def load_file(path: str | Path) -> dict[str, Any]:
    """A config file's content (TOML, YAML or JSON by suffix)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"config file not found: {p}") from None
    except IsADirectoryError:
        raise ConfigError(f"config file {p} is a directory") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"config file {p} is not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    except OSError as exc:
        raise ConfigError(f"config file {p} cannot be read: {exc.strerror or exc}") from None
    try:
        if p.suffix.lower() == ".toml":
            if sys.version_info >= (3, 11):
                import tomllib
            else:  # the same parser, before it joined the standard library
                import tomli as tomllib

            data: Any = tomllib.loads(text)
        elif p.suffix.lower() in (".yaml", ".yml"):
            import yaml

            data = yaml.safe_load(text) or {}
        elif p.suffix.lower() == ".json":
            data = json.loads(text)
        else:
            raise ConfigError(f"config file {p}: use a .toml, .yaml, .yml or .json file")
    except ConfigError:
        raise
    except Exception as exc:  # the parsers' own errors say where (on several lines: one here)
        raise ConfigError(f"config file {p} cannot be read: {_parse_error(exc)}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"config file {p}: the top level must be a table of sections")
    return data


def from_environment(environ: Mapping[str, str] | None = None) -> dict[str, Any]:
    """``TOPOFUSION_ENGINE__A__B=value`` variables as a nested mapping ``{"a": {"b": value}}``
    (a value is read as JSON when it parses, else as a string)."""
    env = os.environ if environ is None else environ
    out: dict[str, Any] = {}
    for name, raw in sorted(env.items()):
        if not name.upper().startswith(ENV_PREFIX):
            continue
        path = [part.lower() for part in name[len(ENV_PREFIX) :].split("__")]
        if not all(path):
            raise ConfigError(f"{name}: empty key in the variable's name")
        try:
            value: Any = json.loads(raw)
        except json.JSONDecodeError:
            value = raw
        node = out
        for part in path[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"{name}: {part} is a value, not a section")
        node[path[-1]] = value
    return out


def merge(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """``over`` on top of ``base``, section by section."""
    out = dict(base)
    for key, value in over.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = merge(out[key], value)
        else:
            out[key] = value
    return out


def _parse_error(exc: Exception) -> str:
    """A parser's error on one line, saying where but never quoting the file: the line it
    shows may hold a secret (an API token)."""
    mark = getattr(exc, "problem_mark", None)  # YAML's: it quotes the line, with a caret
    if mark is not None:
        problem = getattr(exc, "problem", None) or "invalid YAML"
        return f"{problem} at line {mark.line + 1}, column {mark.column + 1}"
    return " ".join(str(exc).split())  # (TOML's and JSON's say the line and column, not the text)
