"""Strict YAML for every configuration file of hp-edge: one loader and one checker.

gateway.yaml, tags.yaml, plant.yaml and simulator.yaml are all read by ``load_yaml`` and checked
with ``Section``/``Problems``, so every command rejects the same things the same way:

* duplicate keys (plain PyYAML keeps the last one silently) and unknown keys, with file, key and
  line;
* anchors and aliases (``&a`` / ``*a``): a configuration has no use for them, and an alias "bomb"
  of a few KB expands to gigabytes;
* nesting deeper than ``MAX_DEPTH`` levels, files larger than ``MAX_BYTES``, text that is not
  UTF-8 or holds control characters (NUL), integers too long to convert, impossible dates.

Every problem is one line ``file: [line N: ][where: ][key 'k': ]message``; ``format_problems``
bounds how many lines and how long each one is, so no input can flood a terminal or the journal.

This module imports nothing from hp-edge but PyYAML, so that ``simulator/`` can use the same loader
without importing the gateway's codec (the simulator encodes registers independently on purpose;
only the parsing of YAML text is shared).
"""
from __future__ import annotations

import difflib
import math
from pathlib import Path
from typing import Any

import yaml

MAX_BYTES = 1_000_000      # a configuration file is a few KB; 1 MB is plenty
MAX_DEPTH = 20             # nesting levels (the shipped files use at most 7)
MAX_PROBLEM_LINES = 50     # printed per run; the rest are counted
MAX_LINE_CHARS = 300       # per printed problem line
MAX_VALUE_CHARS = 60       # a value quoted in a message


class YamlMap(dict):
    """A mapping read from YAML that remembers the line of each key (1-based)."""

    def __init__(self, *args, **kw) -> None:
        super().__init__(*args, **kw)
        self.lines: dict[Any, int] = {}
        self.line: int | None = None


class YamlFileError(ValueError):
    """A YAML file could not be read; ``problems`` holds one line per problem."""

    def __init__(self, problems: list[str]) -> None:
        self.problems = list(problems)
        super().__init__("\n".join(self.problems))


def display_path(path: Path | str) -> str:
    """A path as the user should read it in messages: relative to cwd when inside it."""
    path = Path(path)
    try:
        return str(path.resolve().relative_to(Path.cwd().resolve()))
    except (ValueError, OSError):
        return str(path)


def fmt_value(v: Any) -> str:
    """A value quoted in a message, bounded in length."""
    text = "null" if v is None else repr(v)
    if len(text) > MAX_VALUE_CHARS:
        text = text[: MAX_VALUE_CHARS - 5] + "...'" if text[0] in "'\"" else \
            text[: MAX_VALUE_CHARS - 3] + "..."
    return text


def format_problems(lines: list[str], limit: int = MAX_PROBLEM_LINES) -> list[str]:
    """At most ``limit`` problem lines, each at most MAX_LINE_CHARS long, plus a count of the
    rest."""
    out = [ln if len(ln) <= MAX_LINE_CHARS else ln[: MAX_LINE_CHARS - 3] + "..."
           for ln in lines[:limit]]
    if len(lines) > limit:
        out.append(f"... and {len(lines) - limit} more problem(s)")
    return out


# ------------------------------------------------------------------------------------ loading


class _Refused(yaml.YAMLError):
    def __init__(self, problem: str, mark) -> None:
        self.problem, self.problem_mark = problem, mark
        super().__init__(problem)


class _StrictLoader(yaml.SafeLoader):
    """SafeLoader without anchors/aliases, bounded in depth, recording duplicate keys."""

    def __init__(self, stream) -> None:
        super().__init__(stream)
        self.duplicates: list[tuple[Any, int, int]] = []
        self._depth = 0

    def compose_node(self, parent, index):
        event = self.peek_event()
        if isinstance(event, yaml.AliasEvent):
            raise _Refused(f"alias '*{event.anchor}': anchors and aliases are not allowed in "
                           "hp-edge configuration files; write the value out", event.start_mark)
        if getattr(event, "anchor", None):
            raise _Refused(f"anchor '&{event.anchor}': anchors and aliases are not allowed in "
                           "hp-edge configuration files; write the value out", event.start_mark)
        self._depth += 1
        try:
            if self._depth > MAX_DEPTH:
                raise _Refused(f"nested deeper than {MAX_DEPTH} levels", event.start_mark)
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def construct_object(self, node, deep=False):
        try:
            return super().construct_object(node, deep=deep)
        except (ValueError, OverflowError) as exc:   # e.g. a 5000-digit integer, 2024-02-30
            raise _Refused(f"cannot read the value: {exc}", node.start_mark) from None


def _construct_map(loader: _StrictLoader, node):
    data = YamlMap()
    data.line = node.start_mark.line + 1
    yield data
    loader.flatten_mapping(node)
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node, deep=True)
        try:
            hash(key)
        except TypeError:
            raise _Refused("a mapping key must be a plain value, not a list or mapping",
                           key_node.start_mark) from None
        line = key_node.start_mark.line + 1
        if key in data.lines:
            loader.duplicates.append((key, line, data.lines[key]))
        data[key] = loader.construct_object(value_node, deep=True)
        data.lines[key] = line


_StrictLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_map)


class Problems:
    """Collects problem lines (``file: [line N: ][where: ][key 'k': ]message``)."""

    def __init__(self) -> None:
        self.lines: list[str] = []

    def add(self, file: str, where: str | None, key: Any, msg: str,
            line: int | None = None) -> None:
        if key is not None:
            k = str(key)
            k = k if len(k) <= MAX_VALUE_CHARS else k[: MAX_VALUE_CHARS - 3] + "..."
        parts = [file] + ([f"line {line}"] if line else []) + ([where] if where else []) \
            + ([f"key '{k}'"] if key is not None else [])
        self.lines.append(": ".join(parts) + ": " + msg)


def _syntax_problem(exc: Exception, text: str) -> tuple[str | None, str]:
    if isinstance(exc, yaml.reader.ReaderError):
        line = text[: exc.position].count("\n") + 1 if isinstance(exc.position, int) else None
        what = f"unacceptable character #x{exc.character:04x}" \
            if isinstance(exc.character, int) else "unacceptable byte"
        return (f"line {line}" if line else None), f"{what}: {exc.reason}"
    mark = getattr(exc, "problem_mark", None)
    where = f"line {mark.line + 1} column {mark.column + 1}" if mark is not None else None
    problem = getattr(exc, "problem", None) or str(exc)
    if isinstance(exc, _Refused):
        return where, problem
    return where, f"YAML syntax error: {problem}"


def load_yaml(p: Problems, path: Path, file: str | None = None) -> Any:
    """Parsed YAML (mappings as YamlMap), or None (with the reason recorded on ``p``) when
    unreadable, invalid, refused or empty."""
    file = file or display_path(path)
    try:
        with open(path, "rb") as fh:
            raw = fh.read(MAX_BYTES + 1)
    except FileNotFoundError:
        p.add(file, None, None, "file not found")
        return None
    except IsADirectoryError:
        p.add(file, None, None, "is a directory, not a file")
        return None
    except OSError as exc:
        p.add(file, None, None, f"cannot read: {exc.strerror or exc}")
        return None
    if len(raw) > MAX_BYTES:
        p.add(file, None, None, f"file is larger than {MAX_BYTES} bytes; configuration files "
              "are a few KB")
        return None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        p.add(file, None, None, f"not UTF-8 text (byte 0x{raw[exc.start]:02x} at offset "
              f"{exc.start})")
        return None
    loader = None
    try:
        loader = _StrictLoader(text)      # the reader checks for control characters here
        data = loader.get_single_data()
    except (yaml.YAMLError, RecursionError) as exc:
        if isinstance(exc, RecursionError):
            where, msg = None, f"nested too deeply (more than {MAX_DEPTH} levels)"
        else:
            where, msg = _syntax_problem(exc, text)
        p.add(file, where, None, msg)
        return None
    finally:
        if loader is not None:
            loader.dispose()
    for key, line, first in loader.duplicates:
        p.add(file, f"line {line}", None,
              f"duplicate key {fmt_value(key)} (first at line {first}); YAML would silently "
              "keep the last")
    if data is None:
        p.add(file, None, None, "file is empty")
    return data


def load_yaml_or_raise(path: Path | str, file: str | None = None) -> Any:
    """Like ``load_yaml``, raising YamlFileError with every problem (duplicates included)."""
    p = Problems()
    data = load_yaml(p, Path(path), file)
    if p.lines:
        raise YamlFileError(p.lines)
    return data


def key_line(data: Any, key: Any) -> int | None:
    """Line of ``key`` in a mapping read by ``load_yaml`` (None when unknown)."""
    return data.lines.get(key) if isinstance(data, YamlMap) else None


# ----------------------------------------------------------------------------------- checking

MISSING = object()   # key absent (its absence is reported once, by Section.keys)
REQUIRED = object()


def finite_float(v: Any) -> float | None:
    """``v`` as a finite float, or None when it is not a finite number (bools are not)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    try:
        f = float(v)
    except OverflowError:
        return None
    return f if math.isfinite(f) else None


class Section:
    """One mapping of a YAML file being validated: typed getters that record problems."""

    def __init__(self, p: Problems, file: str, where: str, data: Any) -> None:
        self.p, self.file, self.where, self.data = p, file, where, data

    def problem(self, key: Any, msg: str) -> None:
        self.p.add(self.file, self.where, key, msg, line=key_line(self.data, key))

    def child(self, where: str, data: Any = MISSING) -> Section:
        """A section of the same file (e.g. one advisory field)."""
        return Section(self.p, self.file, where, data)

    def count(self) -> int:
        return len(self.p.lines)

    def mapping(self) -> bool:
        if self.data is MISSING:
            return False
        if not isinstance(self.data, dict):
            self.problem(None, f"expected a mapping of keys, got {fmt_value(self.data)}")
            return False
        return True

    def keys(self, allowed, required=()) -> None:
        for key in self.data:
            if key not in allowed:
                hint = ""
                if isinstance(key, str) and (close := difflib.get_close_matches(key, allowed, 1)):
                    hint = f" (did you mean '{close[0]}'?)"
                self.problem(key, f"unknown key{hint}; allowed: {', '.join(allowed)}")
        for key in required:
            if key not in self.data:
                self.p.add(self.file, self.where, key, "missing required key")

    def has(self, key: str) -> bool:
        return isinstance(self.data, dict) and key in self.data

    def raw(self, key: str) -> Any:
        return self.data.get(key, MISSING) if isinstance(self.data, dict) else MISSING

    def _get(self, key: str, default: Any) -> Any:
        if key in self.data:
            return self.data[key]
        return None if default is REQUIRED else default

    def string(self, key, default=REQUIRED, nullable=False, allow_empty=False):
        if key not in self.data:
            return self._get(key, default)
        v = self.data[key]
        if v is None and nullable:
            return None
        if not isinstance(v, str) or (not v and not allow_empty):
            self.problem(key, f"expected a {'non-empty ' if not allow_empty else ''}string, "
                         f"got {fmt_value(v)}")
            return None
        return v

    def number(self, key, positive=False, default=REQUIRED, lo=None, hi=None):
        if key not in self.data:
            return self._get(key, default)
        v = self.data[key]
        f = finite_float(v)
        if f is None:
            self.problem(key, f"expected a finite number, got {fmt_value(v)}")
            return None
        if positive and f <= 0:
            self.problem(key, f"must be > 0, got {fmt_value(v)}")
            return None
        if (lo is not None and f < lo) or (hi is not None and f > hi):
            self.problem(key, f"{fmt_value(v)} is outside {lo:g}..{hi:g}" if hi is not None
                         else f"must be >= {lo:g}, got {fmt_value(v)}")
            return None
        return f

    def integer(self, key, lo=None, hi=None, default=REQUIRED):
        if key not in self.data:
            return self._get(key, default)
        v = self.data[key]
        if isinstance(v, bool) or not isinstance(v, int):
            self.problem(key, f"expected an integer, got {fmt_value(v)}")
            return None
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            bounds = f"{lo}..{hi}" if hi is not None else f">= {lo}"
            self.problem(key, f"{fmt_value(v)} is outside {bounds}")
            return None
        return v

    def boolean(self, key, default=REQUIRED):
        if key not in self.data:
            return self._get(key, default)
        v = self.data[key]
        if not isinstance(v, bool):
            self.problem(key, f"expected true or false, got {fmt_value(v)}")
            return None
        return v

    def choice(self, key, options, default=REQUIRED):
        if key not in self.data:
            return self._get(key, default)
        v = self.data[key]
        if not isinstance(v, str) or v not in options:
            self.problem(key, f"{fmt_value(v)} is not one of {', '.join(options)}")
            return None
        return v

    def range(self, key):
        if key not in self.data:
            return None
        v = self.data[key]
        ok = isinstance(v, list) and len(v) == 2 and all(finite_float(x) is not None for x in v)
        if not ok:
            self.problem(key, f"expected [low, high] (two numbers), got {fmt_value(v)}")
            return None
        lo, hi = finite_float(v[0]), finite_float(v[1])
        if not lo < hi:
            self.problem(key, f"low {fmt_value(v[0])} must be below high {fmt_value(v[1])}")
            return None
        return (lo, hi)

    def path(self, key, base: Path, must_exist=False):
        v = self.string(key)
        if v is None:
            return None
        if "\x00" in v:
            self.problem(key, "a path cannot contain a NUL character")
            return None
        try:
            resolved = (base / Path(v).expanduser()).resolve()
        except (OSError, RuntimeError, ValueError) as exc:
            self.problem(key, f"not a usable path: {exc}")
            return None
        try:
            if must_exist and not resolved.is_file():
                what = "is not a file" if resolved.exists() else "file not found"
                self.problem(key, f"{what}: {display_path(resolved)}")
                return None
        except OSError as exc:     # e.g. a name too long for the file system
            self.problem(key, f"not a usable path: {exc.strerror or exc}")
            return None
        return resolved


def check_schema(sec: Section, schema: dict, path: str = "") -> None:
    """Reject unknown keys at every level of ``sec.data`` that ``schema`` describes.

    ``schema`` maps each allowed key to: None (a value, checked elsewhere), a dict (a nested
    section with its own allowed keys), or ``MapOf(schema)`` (a mapping whose keys are names the
    user chooses, e.g. calibration parameters, each value checked against ``schema``). Values
    are checked by whoever reads them; this function only makes sure no key is ignored."""
    if not sec.mapping():
        return
    sec.keys(tuple(schema))
    for key, sub in schema.items():
        if sub is None or key not in sec.data:
            continue
        where = f"{path}.{key}" if path else str(key)
        child = sec.child(f"section '{where}'", sec.data[key])
        if isinstance(sub, MapOf):
            if sec.data[key] is None:
                continue
            if not child.mapping():
                continue
            for name, body in child.data.items():
                if sub.schema is None:
                    continue
                check_schema(child.child(f"section '{where}.{name}'", body), sub.schema,
                             f"{where}.{name}")
        else:
            if sec.data[key] is None:
                continue
            check_schema(child, sub, where)


class MapOf:
    """Schema of a mapping with user-chosen keys, each value a section of ``schema`` (or any
    value when ``schema`` is None)."""

    def __init__(self, schema: dict | None) -> None:
        self.schema = schema
