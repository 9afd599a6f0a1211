"""Declarative configuration: dataclass fields that carry their help, flag and checks, so
command-line flags, YAML loading and the reference page come from one declaration.

A configuration class is a dataclass whose fields are made with :func:`setting`. From it:

* :func:`add_flags` adds one command-line flag per field (``--sequence-length`` for
  ``sequence_length`` unless the field names another), typed from the field's default,
  booleans as ``--x`` / ``--no-x``; :func:`flag_values` reads back the flags that were given;
* :func:`load_yaml` reads a YAML file whose floats may be written ``1e-4`` (YAML 1.2; PyYAML's
  YAML 1.1 would read a string), with errors naming the file;
* :func:`reference_markdown` renders the reference table (docs/config.md);
* the validators every field uses are in ``v2v_server.checks`` (below every stage, which
  validates its own mappings with them).

A class may compose others (``PARTS``, ``(attribute, class)`` pairs): each part declares its own
keys once, and the composition takes and gives them flat, as users write them
(:func:`documented`, :func:`owners`, :func:`split_keys`).

Dataclasses rather than pydantic: no dependency for a decode host, and the checks here are a
handful of small functions; a worker process imports this module in well under a millisecond.
"""
from __future__ import annotations

import argparse
import dataclasses
import re
from pathlib import Path
from typing import Any, Dict, Iterable, List, Optional, Sequence

import yaml

from v2v_server.checks import check_keys

__all__ = ["setting", "documented", "owners", "split_keys", "add_flags", "flag_values", "load_yaml",
           "reference_markdown", "YamlLoader"]


def setting(default: Any = dataclasses.MISSING, *, help: str, flag: Optional[str] = None, group: str = "",
            choices: Optional[Sequence] = None, cli: Optional[type] = None, factory: Any = dataclasses.MISSING):
    """A dataclass field with its documentation.

    Args:
        default / factory: the default value (or a zero-argument factory for mutable ones).
        help: one line for ``--help`` and the reference page.
        flag: the command-line flag (default ``--`` + the name with dashes); ``""`` for a
            field set in YAML only (mappings, lists of ranges).
        group: heading on the reference page (the field's class name when empty).
        choices: allowed values, for ``--help`` and argparse.
        cli: the type a flag parses to, when not the default's (e.g. ``str`` for a comma list).
    """
    meta = {"help": help, "flag": flag, "group": group, "choices": tuple(choices) if choices else None, "cli": cli}
    if factory is not dataclasses.MISSING:
        return dataclasses.field(default_factory=factory, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def documented(cls) -> List[dataclasses.Field]:
    """The fields of ``cls`` made with :func:`setting`, in order, then, for a composition of
    settings classes (a class with ``PARTS``, ``(attribute, class)`` pairs), those of every part."""
    return _own(cls) + [f for _, part in getattr(cls, "PARTS", ()) for f in documented(part)]


def _own(cls) -> List[dataclasses.Field]:
    """The fields ``cls`` itself declares with :func:`setting` (none for a class that only composes)."""
    return [f for f in dataclasses.fields(cls) if "help" in f.metadata] if dataclasses.is_dataclass(cls) else []


def owners(cls) -> Dict[str, str]:
    """Flat key -> the attribute of the part of ``cls`` that declares it (``""``: ``cls`` itself),
    for every key :func:`documented` gives."""
    out = {f.name: "" for f in _own(cls)}
    for attr, part in getattr(cls, "PARTS", ()):
        out.update((f.name, attr) for f in documented(part))
    return out


def split_keys(cls, keys: dict) -> Dict[str, dict]:
    """``keys`` (flat, as users write them) grouped by the part of ``cls`` that declares each
    (:func:`owners`): ``{"": cls's own, attribute: that part's, ...}``, every group present.

    Raises:
        ValueError: naming every unknown key and the allowed ones (``checks.check_keys``).
    """
    owner = owners(cls)
    check_keys(keys, owner)
    groups: Dict[str, dict] = {"": {}, **{attr: {} for attr, _ in getattr(cls, "PARTS", ())}}
    for k, v in keys.items():
        groups[owner[k]][k] = v
    return groups


def _flag(f: dataclasses.Field) -> str:
    flag = f.metadata.get("flag")
    return ("--" + f.name.replace("_", "-")) if flag is None else flag


def _default(f: dataclasses.Field):
    return f.default_factory() if f.default is dataclasses.MISSING else f.default


def _cli_type(f: dataclasses.Field) -> Optional[type]:
    if f.metadata.get("cli"):
        return f.metadata["cli"]
    ann = str(f.type)
    for name, t in (("bool", bool), ("int", int), ("float", float), ("str", str)):
        if re.fullmatch(rf"(Optional\[)?{name}\]?", ann):
            return t
    return None


def add_flags(parser: argparse.ArgumentParser, cls, title: Optional[str] = None,
              only: Optional[Sequence[str]] = None) -> None:
    """One flag per documented scalar field of ``cls`` (or of those named in ``only``):
    ``dest`` = the field name, default None so that :func:`flag_values` knows what was given."""
    target = parser.add_argument_group(title) if title else parser
    for f in documented(cls):
        if only is not None and f.name not in only:
            continue
        t, flag = _cli_type(f), _flag(f)
        if t is None or not flag:
            continue
        d = _default(f)
        text = f.metadata["help"] + ("" if d is None or d == "" else f" (default {_show(d)})")
        if t is bool:
            target.add_argument(flag, dest=f.name, action=argparse.BooleanOptionalAction, default=None, help=text)
        else:
            target.add_argument(flag, dest=f.name, type=t, default=None, choices=f.metadata.get("choices"), help=text)


def flag_values(args: argparse.Namespace, cls) -> dict:
    """The fields of ``cls`` given on the command line: ``{name: value}``."""
    return {f.name: getattr(args, f.name) for f in documented(cls)
            if getattr(args, f.name, None) is not None}


class YamlLoader(yaml.SafeLoader):
    """SafeLoader that reads YAML 1.2 scalars: floats such as ``1.0e9`` or ``1e-3`` as numbers
    (YAML 1.1, PyYAML's default, reads them as strings), and only ``true`` / ``false`` as
    booleans (YAML 1.1 also reads ``on``, ``off``, ``yes``, ``no``: ``shot_cuts: off`` or
    ``decode_fast: off`` would arrive as ``False``)."""


# YAML 1.2's booleans: the YAML 1.1 resolver (yes/no/on/off) is replaced
YamlLoader.yaml_implicit_resolvers = {
    k: [(tag, rx) for tag, rx in v if tag != "tag:yaml.org,2002:bool"]
    for k, v in yaml.SafeLoader.yaml_implicit_resolvers.items()}
YamlLoader.add_implicit_resolver("tag:yaml.org,2002:bool", re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"),
                                 list("tTfF"))


YamlLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
                |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
                |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
                |[-+]?\.(?:inf|Inf|INF)
                |\.(?:nan|NaN|NAN))$""", re.X),
    list("-+0123456789."))


def load_yaml(path) -> dict:
    """The mapping in the YAML file at ``path``.

    Raises:
        FileNotFoundError: no such file.
        ValueError: naming the file, when it is not valid YAML or not a mapping.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"config file not found: {p}")
    try:
        data = yaml.load(p.read_text(), Loader=YamlLoader) or {}
    except yaml.YAMLError as e:
        raise ValueError(f"{p}: not valid YAML: {e}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{p}: top level must be a mapping of keys to values")
    return data


def _show(v) -> str:
    if isinstance(v, (tuple, list)):
        return ",".join(str(x) for x in v)
    if dataclasses.is_dataclass(v):
        return "see below"
    return "{}" if v == {} else str(v)


def reference_markdown(cls, groups: Iterable, flag_of=None) -> str:
    """The reference table of ``cls``'s fields, one section per class of ``groups`` (the
    dataclasses ``cls`` is made of, in order): key, flag, default, meaning. ``flag_of(field)``,
    when given, names how the command line sets a field instead of its flag."""
    out = []
    for g in groups:
        out += [f"## {g.__doc__.strip().splitlines()[0]}", "", "| key | flag | default | meaning |", "|---|---|---|---|"]
        own = {f.name for f in documented(g)}
        for f in documented(cls):
            if f.name not in own:
                continue
            flag = f"`{_flag(f)}`" if _flag(f) and _cli_type(f) else "(YAML only)"
            if flag_of is not None:
                flag = flag_of(f)
            choices = f.metadata.get("choices")
            meaning = f.metadata["help"] + (f" ({' / '.join(map(str, choices))})" if choices else "")
            meaning = meaning.replace("|", "\\|")  # a table cell
            out.append(f"| `{f.name}` | {flag} | `{_show(_default(f))}` | {meaning} |")
        out.append("")
    return "\n".join(out)
