"""Command-line flags and TOML config files generated from frozen dataclass configs.

Each default is written once, in the dataclass; each flag's help is the field's docstring. Nested
dataclass fields become prefixed flags (``index: IndexConfig`` gives ``--index-rank``) and TOML tables
(``[index]``); a field may also answer to a shorter alias (``--grad-threshold``). Precedence: command
line, then the config file, then a command's own defaults, then the dataclass default (or a ``base``
instance, e.g. a schedule compressed to fewer steps). Imports nothing heavy, so ``--help`` stays fast.
Field types: bool, int, float, str, Path, tuples of numbers ("0,0,0" on the command line), their
Optional forms ("none" on the command line), nested dataclasses; dict fields are TOML-only tables.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import itertools
import math
import textwrap
import tomllib
import types
import typing
from pathlib import Path
from typing import Any

UNSET = object()
"""The default of every flag ``add_flags`` generates: an argparse value that is still ``UNSET`` was not
given on the command line, so the config file or the default applies."""


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


def _float(s: str) -> float:
    """A float flag's value; NaN is no setting (every comparison with it is false, so no check holds)."""
    try:
        v = float(s)
    except ValueError:
        v = math.nan
    if math.isnan(v):
        raise argparse.ArgumentTypeError(f"expected a number, got {s!r}")
    return v


def _tuple_parser(tp: Any):
    items = typing.get_args(tp)
    conv = int if items and items[0] is int else _float

    def parse(s: str) -> tuple:
        try:
            vals = tuple(conv(v) for v in s.split(","))
        except (ValueError, argparse.ArgumentTypeError) as e:
            raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {s!r}") from e
        if items and Ellipsis not in items and len(vals) != len(items):
            raise argparse.ArgumentTypeError(f"expected {len(items)} comma-separated numbers, got {s!r}")
        return vals

    return parse


def _parser_for(tp: Any, optional: bool):
    if tp is Path:
        conv = Path
    elif tp is float:
        conv = _float
    elif tp in (int, str):
        conv = tp
    elif typing.get_origin(tp) is tuple:
        conv = _tuple_parser(tp)
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


def add_flags(
    parser: argparse.ArgumentParser | argparse._ArgumentGroup,
    cls: type,
    prefix: str = "",
    aliases: dict[str, str] | None = None,
    defaults: dict[str, Any] | None = None,
    skip: tuple[str, ...] = (),
) -> None:
    """Add ``--<prefix><field-name>`` for every field of ``cls`` (recursing into dataclass fields).

    aliases: dotted field name -> another option string for it (``{"densify.grad_threshold":
    "--grad-threshold"}``); defaults: dotted field name -> the command's own default (shown in the help;
    pass the same mapping to ``config_from``); skip: dotted names left to the config file or the command.
    """
    aliases, defaults = aliases or {}, defaults or {}
    docs = field_docs(cls)
    for f, tp in _fields(cls):
        name = prefix + f.name
        if name in skip:
            continue
        flag = "--" + name.replace("_", "-").replace(".", "-")
        if dataclasses.is_dataclass(tp):
            add_flags(parser, tp, name + ".", aliases, defaults, skip)
            continue
        base, optional = _base(tp)
        if base is dict or typing.get_origin(base) is dict:
            continue  # free-form tables: config files only
        if name in defaults:
            default = defaults[name]
        elif f.default is not dataclasses.MISSING:
            default = f.default
        elif f.default_factory is not dataclasses.MISSING:
            default = f.default_factory()
        else:
            default = "required"
        doc = docs.get(f.name, "")
        help_ = f"{doc} (default: {default})" if doc else f"default: {default}"
        names = [flag, *([aliases[name]] if name in aliases else [])]
        if base is bool:
            parser.add_argument(
                *names, dest=name, action=argparse.BooleanOptionalAction, default=UNSET, help=help_
            )
        else:
            conv = _parser_for(base, optional)
            meta = getattr(base, "__name__", "VALUES").upper()
            parser.add_argument(*names, dest=name, type=conv, default=UNSET, metavar=meta, help=help_)


def _build(cls: type, values: dict[str, Any], where: str, base: Any = None) -> Any:
    kw: dict[str, Any] = {}
    known = {f.name: tp for f, tp in _fields(cls)}
    for key, val in values.items():
        if key not in known:
            raise ValueError(f"{where}: unknown setting {key!r} (known: {', '.join(sorted(known))})")
        tp = known[key]
        if dataclasses.is_dataclass(tp):
            if not isinstance(val, dict):
                raise ValueError(f"{where}: {key} must be a table")
            inner = getattr(base, key) if base is not None else None
            kw[key] = _build(tp, val, f"{where}.{key}", inner)
            continue
        kw[key] = _value(tp, val, f"{where}: {key}")
    try:
        return dataclasses.replace(base, **kw) if base is not None else cls(**kw)
    except TypeError as e:  # a required setting is missing
        raise ValueError(f"{where}: {e}") from e


def _value(tp: Any, val: Any, what: str) -> Any:
    base, optional = _base(tp)
    if val is None and optional:
        return None
    if base is bool:
        if not isinstance(val, bool):
            raise ValueError(f"{what} must be true or false, got {val!r}")
        return val
    if base in (int, float):
        ok = isinstance(val, int | float) and not isinstance(val, bool)
        if not ok or (base is int and isinstance(val, float) and not val.is_integer()):
            raise ValueError(f"{what} must be {base.__name__}, got {val!r}")
        if isinstance(val, float) and math.isnan(val):
            raise ValueError(f"{what} must be a number, got nan")
        return base(val)
    if typing.get_origin(base) is tuple:
        if isinstance(val, str):
            try:
                return _tuple_parser(base)(val)
            except argparse.ArgumentTypeError as e:
                raise ValueError(f"{what}: {e}") from e
        if not isinstance(val, list | tuple) or not all(_is_num(v) and v == v for v in val):
            raise ValueError(f"{what} must be a list of numbers, got {val!r}")
        items = typing.get_args(base)
        if items and Ellipsis not in items and len(val) != len(items):
            raise ValueError(f"{what} must hold {len(items)} numbers, got {len(val)}")
        return tuple(val)
    if base is dict or typing.get_origin(base) is dict:
        if not isinstance(val, dict):
            raise ValueError(f"{what} must be a table, got {val!r}")
        return dict(val)
    if not isinstance(val, str | Path):  # str or Path
        raise ValueError(f"{what} must be a string, got {val!r}")
    return base(val)


def _is_num(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


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


def values_from(
    cls: type,
    args: argparse.Namespace,
    config_file: str | Path | None = None,
    defaults: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The settings given for ``cls`` (nested dicts): flags over the TOML file over ``defaults``."""
    file_values: dict[str, Any] = {}
    if config_file is not None:
        try:
            file_values = tomllib.loads(Path(config_file).read_text())
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as e:
            raise ValueError(f"cannot read config file {config_file}: {e}") from e
    given = {k: v for k, v in vars(args).items() if v is not UNSET and _is_field(cls, k)}
    return _merge(_merge(_nest(defaults or {}), file_values), _nest(given))


def config_from(
    cls: type,
    args: argparse.Namespace,
    config_file: str | Path | None = None,
    defaults: dict[str, Any] | None = None,
    base: Any = None,
) -> Any:
    """An instance of ``cls``: flags given on the command line over the TOML file over ``defaults`` over
    ``base`` (an instance; default: the dataclass defaults)."""
    values = values_from(cls, args, config_file, defaults)
    return build(cls, values, str(config_file or "flags"), base)


def build(cls: type, values: dict[str, Any], where: str = "settings", base: Any = None) -> Any:
    """An instance of ``cls`` from nested ``values`` (unknown keys and wrong types named) over ``base``."""
    return _build(cls, values, where, base)


def _is_field(cls: type, dotted: str) -> bool:
    head, _, rest = dotted.partition(".")
    for f, tp in _fields(cls):
        if f.name == head:
            return _is_field(tp, rest) if rest and dataclasses.is_dataclass(tp) else not rest
    return False
