"""Command-line flags and TOML config files generated from frozen dataclass configs.

Each default is written once, in the dataclass; each flag's help is the field's docstring. Nested
dataclass fields become prefixed flags (``index: IndexConfig`` gives ``--index-rank``) and TOML tables
(``[index]``). Precedence: command line, then the config file, then the dataclass default. Imports
nothing heavy, so ``--help`` stays fast.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import itertools
import textwrap
import tomllib
import types
import typing
from pathlib import Path
from typing import Any

_UNSET = object()


def field_docs(cls: type) -> dict[str, str]:
    """The docstring written under each field of dataclass ``cls`` (empty when it has none)."""
    try:
        tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    except (OSError, TypeError):
        return {}
    body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
    docs: dict[str, str] = {}
    for a, b in itertools.pairwise(body):
        if (
            isinstance(a, ast.AnnAssign)
            and isinstance(a.target, ast.Name)
            and isinstance(b, ast.Expr)
            and isinstance(b.value, ast.Constant)
            and isinstance(b.value.value, str)
        ):
            docs[a.target.id] = " ".join(b.value.value.split())
    return docs


def _base(tp: Any) -> tuple[Any, bool]:
    """(type without Optional, whether None is allowed)."""
    if isinstance(tp, types.UnionType) or typing.get_origin(tp) is typing.Union:
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        return (args[0] if len(args) == 1 else str), True
    return tp, False


def _parser_for(tp: Any, optional: bool):
    if tp is Path:
        conv = Path
    elif tp in (int, float, str):
        conv = tp
    else:
        raise TypeError(f"no flag for fields of type {tp!r}")
    if not optional:
        return conv

    def parse(s: str):
        return None if s.lower() in ("", "none") else conv(s)

    return parse


def _fields(cls: type) -> list[tuple[dataclasses.Field, Any]]:
    hints = typing.get_type_hints(cls)
    return [(f, hints[f.name]) for f in dataclasses.fields(cls) if f.init]


def add_flags(parser: argparse.ArgumentParser, cls: type, prefix: str = "") -> None:
    """Add ``--<prefix><field-name>`` for every field of ``cls`` (recursing into dataclass fields)."""
    docs = field_docs(cls)
    for f, tp in _fields(cls):
        name = prefix + f.name
        flag = "--" + name.replace("_", "-").replace(".", "-")
        if dataclasses.is_dataclass(tp):
            add_flags(parser, tp, name + ".")
            continue
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        doc = docs.get(f.name, "")
        help_ = f"{doc} (default: {default})" if doc else f"default: {default}"
        base, optional = _base(tp)
        if base is bool:
            parser.add_argument(
                flag, dest=name, action=argparse.BooleanOptionalAction, default=_UNSET, help=help_
            )
        else:
            conv = _parser_for(base, optional)
            meta = base.__name__.upper()
            parser.add_argument(flag, dest=name, type=conv, default=_UNSET, metavar=meta, help=help_)


def _build(cls: type, values: dict[str, Any], where: str) -> Any:
    kw: dict[str, Any] = {}
    known = {f.name: tp for f, tp in _fields(cls)}
    for key, val in values.items():
        if key not in known:
            raise ValueError(f"{where}: unknown setting {key!r} (known: {', '.join(sorted(known))})")
        tp = known[key]
        if dataclasses.is_dataclass(tp):
            if not isinstance(val, dict):
                raise ValueError(f"{where}: {key} must be a table")
            kw[key] = _build(tp, val, f"{where}.{key}")
            continue
        base, optional = _base(tp)
        if val is None and optional:
            kw[key] = None
        elif base is bool:
            if not isinstance(val, bool):
                raise ValueError(f"{where}: {key} must be true or false, got {val!r}")
            kw[key] = val
        elif base in (int, float):
            ok = isinstance(val, int | float) and not isinstance(val, bool)
            if not ok or (base is int and isinstance(val, float) and not val.is_integer()):
                raise ValueError(f"{where}: {key} must be {base.__name__}, got {val!r}")
            kw[key] = base(val)
        else:  # str or Path
            if not isinstance(val, str | Path):
                raise ValueError(f"{where}: {key} must be a string, got {val!r}")
            kw[key] = base(val)
    return cls(**kw)


def _nest(flat: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, val in flat.items():
        *parents, leaf = key.split(".")
        d = out
        for p in parents:
            d = d.setdefault(p, {})
        d[leaf] = val
    return out


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def config_from(cls: type, args: argparse.Namespace, config_file: str | Path | None = None) -> Any:
    """An instance of ``cls``: flags given on the command line over the TOML file over the defaults."""
    file_values: dict[str, Any] = {}
    if config_file is not None:
        try:
            file_values = tomllib.loads(Path(config_file).read_text())
        except (OSError, tomllib.TOMLDecodeError) as e:
            raise ValueError(f"cannot read config file {config_file}: {e}") from e
    given = {k: v for k, v in vars(args).items() if v is not _UNSET and _is_field(cls, k)}
    return _build(cls, _merge(file_values, _nest(given)), str(config_file or "flags"))


def _is_field(cls: type, dotted: str) -> bool:
    head, _, rest = dotted.partition(".")
    for f, tp in _fields(cls):
        if f.name == head:
            return _is_field(tp, rest) if rest and dataclasses.is_dataclass(tp) else not rest
    return False
