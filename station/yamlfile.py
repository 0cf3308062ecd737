"""THE YAML loader of the station: every model, world, cell, limits and procedure file is read here.

A file is a careless operator's or a malicious author's, so the loader is strict (docs/formats.md):

- regular files only (a FIFO, ``/dev/zero`` or a directory is refused before it is read), at most
  ``MAX_BYTES``; UTF-8 text only (UTF-16, other encodings and binary data are refused with the line);
- no aliases (``*name``): an alias bomb ("billion laughs") cannot expand; nesting at most ``MAX_DEPTH``;
- duplicate keys refused (the last one does not silently win);
- YAML 1.2 core scalars only: ``1_0``, ``0b1``, ``1:30``, ``yes``/``on`` and dates stay strings, ``010`` is
  ten, integers have at most ``MAX_INT_DIGITS`` digits; non-ASCII digits (``١``) are never numbers.

The parsed document keeps the line of every key and item (``YamlDoc.line``) so a reader's error names it:
``FILE:LINE: FIELD: what is wrong``."""

from __future__ import annotations

import re
from pathlib import Path

import yaml
from yaml.events import AliasEvent

# the strict reading of a text file and a parsed file's shape live where no yaml is imported (station.textfile)
from station.textfile import MAX_BYTES, YamlDoc, decode, dotted, read_capped  # noqa: F401

MAX_DEPTH = 64  # nesting of mappings and lists
MAX_INT_DIGITS = 30  # beyond any physical quantity in any unit; a 400-digit integer is not a reading


class _Refused(yaml.YAMLError):
    def __init__(self, problem: str, mark=None):
        super().__init__(problem)
        self.problem, self.problem_mark = problem, mark


class StrictLoader(yaml.SafeLoader):
    """SafeLoader with YAML 1.2 core scalars, no aliases, a depth cap, duplicate keys refused and the line of
    every mapping key and list item recorded (``self.lines``: id(container) -> {key or index: line})."""

    yaml_implicit_resolvers: dict = {}

    def __init__(self, stream):
        super().__init__(stream)
        self.depth = 0
        self.lines: dict[int, dict] = {}

    def compose_node(self, parent, index):
        if self.check_event(AliasEvent):
            event = self.peek_event()
            raise _Refused(f"alias *{event.anchor} refused (aliases are not accepted; write the value out)",
                           event.start_mark)
        self.depth += 1
        if self.depth > MAX_DEPTH:
            raise _Refused(f"nested deeper than {MAX_DEPTH} levels", self.peek_event().start_mark)
        try:
            return super().compose_node(parent, index)
        finally:
            self.depth -= 1


def _construct_map(loader: StrictLoader, node):
    data: dict = {}
    yield data
    lines = loader.lines.setdefault(id(data), {})
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node, deep=True)
        try:
            hash(key)
        except TypeError:
            raise _Refused("a mapping key must be a plain value", key_node.start_mark) from None
        if key in data:
            raise _Refused(f"duplicate key {key!r} (first on line {lines[key]})", key_node.start_mark)
        data[key] = loader.construct_object(value_node, deep=True)
        lines[key] = key_node.start_mark.line + 1


def _construct_seq(loader: StrictLoader, node):
    data: list = []
    yield data
    data.extend(loader.construct_object(n, deep=True) for n in node.value)
    loader.lines[id(data)] = {i: n.start_mark.line + 1 for i, n in enumerate(node.value)}


def _construct_int(loader: StrictLoader, node):
    text = loader.construct_scalar(node)
    digits = text.lstrip("+-")
    if len(digits) > MAX_INT_DIGITS:
        raise _Refused(f"integer with {len(digits)} digits is out of range", node.start_mark)
    if digits[:2] in ("0x", "0o"):
        return int(digits[2:], 16 if digits[1] == "x" else 8)
    return int(text, 10)


def _construct_float(loader: StrictLoader, node):
    text = loader.construct_scalar(node).lower()
    if text.lstrip("+-") == ".inf":
        return float("-inf") if text.startswith("-") else float("inf")
    if text == ".nan":
        return float("nan")
    return float(text)


# YAML 1.2 core schema (https://yaml.org/spec/1.2.2/#1032-tag-resolution); first characters as PyYAML wants
for _tag, _pattern, _first in (
    ("bool", r"true|True|TRUE|false|False|FALSE", "tTfF"),
    ("int", r"[-+]?[0-9]+|0o[0-7]+|0x[0-9a-fA-F]+", "-+0123456789"),
    ("float", r"[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN)",
     "-+0123456789."),
    ("null", r"~|null|Null|NULL|", ["~", "n", "N", ""]),
):
    StrictLoader.add_implicit_resolver(f"tag:yaml.org,2002:{_tag}", re.compile(rf"^(?:{_pattern})$", re.ASCII),
                                       list(_first))
StrictLoader.add_constructor("tag:yaml.org,2002:map", _construct_map)
StrictLoader.add_constructor("tag:yaml.org,2002:seq", _construct_seq)
StrictLoader.add_constructor("tag:yaml.org,2002:int", _construct_int)
StrictLoader.add_constructor("tag:yaml.org,2002:float", _construct_float)


def _refuse_tag(loader: StrictLoader, node):
    raise _Refused(f"tag {node.tag} refused (plain values, mappings and lists only)", node.start_mark)


for _tag in ("omap", "pairs", "set", "timestamp", "binary", "merge", "value", "yaml"):  # no Python-only shapes
    StrictLoader.add_constructor(f"tag:yaml.org,2002:{_tag}", _refuse_tag)


class _ShippedLoader(getattr(yaml, "cyaml", None) and yaml.cyaml.CParser or yaml.SafeLoader,
                     yaml.constructor.SafeConstructor, yaml.resolver.Resolver):
    """StrictLoader's scalars, constructors and line record on libyaml's parser (~10x faster than the pure
    Python one: ~15 ms of every command that loads a built-in model; bench/startup.py). For the station's own package
    data only: its composer does not refuse aliases or deep nesting, which shipped files do not have
    (tests/cli/test_startup.py parses every built-in both ways and compares)."""

    yaml_constructors = StrictLoader.yaml_constructors
    yaml_implicit_resolvers = StrictLoader.yaml_implicit_resolvers

    def __init__(self, stream):
        super().__init__(stream)
        yaml.constructor.SafeConstructor.__init__(self)
        yaml.resolver.Resolver.__init__(self)
        self.depth = 0
        self.lines: dict[int, dict] = {}


def _paths(data, lines_by_id: dict, prefix: tuple, out: dict) -> None:
    if isinstance(data, dict | list):
        lines = lines_by_id.get(id(data), {})
        for k, v in (data.items() if isinstance(data, dict) else enumerate(data)):
            if k in lines:
                out[prefix + (k,)] = lines[k]
            _paths(v, lines_by_id, prefix + (k,), out)


def parse_yaml_doc(text: str | bytes, error: type[Exception], name: str, *, shipped: bool = False) -> YamlDoc:
    """Parse ``text`` (of file ``name``) strictly; ``error(message)`` for anything refused:
    ``NAME:LINE: not valid YAML (problem)``. ``shipped``: the station's own package data, parsed by libyaml
    (``_ShippedLoader``)."""
    text = decode(text if isinstance(text, bytes) else text.encode("utf-8", "surrogatepass"), error, name)
    if len(text) > MAX_BYTES:
        raise error(f"{name}: larger than {MAX_BYTES // 1024 // 1024} MiB; refused")
    loader = None
    try:
        loader = (_ShippedLoader if shipped else StrictLoader)(text)
        data = loader.get_single_data()
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        head = f"{name}:{mark.line + 1}" if mark else name
        problem = getattr(e, "problem", None) or str(e).splitlines()[0]
        raise error(f"{head}: not valid YAML ({problem})") from None
    except (RecursionError, MemoryError, ValueError, TypeError) as e:  # cannot happen with the caps; belt and braces
        raise error(f"{name}: not valid YAML ({type(e).__name__})") from None
    finally:
        if loader is not None:
            loader.dispose()
    lines: dict[tuple, int] = {}
    _paths(data, loader.lines, (), lines)
    return YamlDoc(name, data, lines)


def parse_yaml(text: str | bytes, error: type[Exception], name: str):
    """Parsed content of ``text`` (the bytes of file ``name``, e.g. kept for a checksum); see ``parse_yaml_doc``."""
    return parse_yaml_doc(text, error, name).data


def load_yaml_doc(path: str | Path, error: type[Exception], what: str = "", hint: str = "") -> YamlDoc:
    """Parsed ``path`` with the line of every field; ``error(message)`` for an unreadable file or bad YAML.
    ``what`` prefixes the path (e.g. ``"cell file"``), ``hint`` is appended to a read error."""
    name = f"{what} {path}" if what else str(path)
    return parse_yaml_doc(read_capped(path, error, name, hint=hint), error, name)


def load_yaml(path: str | Path, error: type[Exception], what: str = "", hint: str = ""):
    """Parsed content of ``path``; see ``load_yaml_doc``."""
    return load_yaml_doc(path, error, what, hint).data
