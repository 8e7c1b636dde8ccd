"""Structured text (YAML and JSON) read strictly: every problem one line naming the file.

YAML is read as version 1.2's core schema reads numbers, a key given twice in a mapping is an
error in both formats, and a text whose aliases stand for a structure without end (or far
larger than the file) is refused before anything walks it. :func:`parse_problem` turns a
parser's error into ``line L:C: problem``; :func:`read_config_text` reads a config-like file's
text or says in one line why it cannot.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import yaml

from spacepose.errors import ConfigError


def parse_problem(exc: Exception) -> str:
    """``line L:C: problem`` of a YAML or JSON parse error, on one line.

    PyYAML's message spans several lines (the context, the offending line and a caret); this
    keeps the position of the problem and the problem itself, and the context in brackets.
    """
    if isinstance(exc, json.JSONDecodeError):
        return f"line {exc.lineno}:{exc.colno}: {exc.msg}"
    mark = getattr(exc, "problem_mark", None)
    problem = getattr(exc, "problem", None)
    if problem is None:
        return " ".join(str(exc).split())
    where = f"line {mark.line + 1}:{mark.column + 1}: " if mark is not None else ""
    context = getattr(exc, "context", None)
    return f"{where}{problem}" + (f" ({context})" if context else "")


class _UniqueKeyLoader(yaml.SafeLoader):
    """YAML's safe loader, refusing a mapping that gives a key twice."""


def _unique_mapping(loader: _UniqueKeyLoader, node: yaml.MappingNode, deep: bool = False) -> Any:
    # PyYAML keeps the last of two equal keys without a word: a config's first value of a
    # knob would be ignored silently.
    seen: set[Any] = set()
    for key_node, _ in node.value:
        if key_node.tag == "tag:yaml.org,2002:merge":  # "<<: *base" merges, as it may
            continue
        key = loader.construct_object(key_node, deep=True)
        try:
            twice = key in seen
            seen.add(key)
        except TypeError:  # an unhashable key: construct_mapping says so
            break
        if twice:
            problem = f"the key {key!r} is given twice"
            raise yaml.constructor.ConstructorError(None, None, problem, key_node.start_mark)
    return loader.construct_mapping(node, deep=deep)


_UniqueKeyLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _unique_mapping)
# Numbers as YAML 1.2's core schema reads them, not YAML 1.1's, which PyYAML follows: 1.1 reads
# 1e5 as text, 010 as 8 (octal), 1:30 as 90 (base 60) and 1_000 as 1000. Here 1e5 is a number,
# 010 is 10, and 1:30 and 1_000 are text, which a config then refuses as a number given as
# text (refuse_text_number) instead of reading a value the user did not write.
_INT, _FLOAT = "tag:yaml.org,2002:int", "tag:yaml.org,2002:float"
_UniqueKeyLoader.yaml_implicit_resolvers = {
    first: [(tag, rx) for tag, rx in resolvers if tag not in (_INT, _FLOAT)]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
_UniqueKeyLoader.add_implicit_resolver(
    _INT, re.compile(r"^(?:[-+]?[0-9]+|0o[0-7]+|0x[0-9a-fA-F]+)$"), list("-+0123456789")
)
_UniqueKeyLoader.add_implicit_resolver(
    _FLOAT,
    re.compile(
        r"^(?:[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?"
        r"|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$"
    ),
    list("-+.0123456789"),
)


def _core_int(loader: _UniqueKeyLoader, node: yaml.ScalarNode) -> int:
    """An integer as YAML 1.2 writes it: decimal (leading zeros too), 0o octal, 0x hex."""
    text = loader.construct_scalar(node)
    if text[:2] in ("0o", "0x"):
        return int(text[2:], 8 if text[1] == "o" else 16)
    return int(text, 10)


_UniqueKeyLoader.add_constructor(_INT, _core_int)


def _unique_pairs(text: str) -> Any:
    """``object_pairs_hook`` of :func:`json.loads` refusing an object that gives a key twice."""

    def hook(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
        keys = [k for k, _ in pairs]
        twice = next((k for k in keys if keys.count(k) > 1), None)
        if twice is not None:
            at = max(text.rfind(json.dumps(twice)), 0)
            raise json.JSONDecodeError(f"the key {twice!r} is given twice", text, at)
        return dict(pairs)

    return hook


def load_structured(text: str, kind: str) -> Any:
    """``json.loads`` (``kind == "json"``) or ``yaml.safe_load`` of ``text``, refusing a key
    given twice in one mapping.

    Both parsers recurse once per level of nesting, so ``[[[[…`` a few thousand deep ends in a
    RecursionError; it is raised as the parser's own error (``nested too deeply``), which every
    reader already turns into one line naming its file. So is the ValueError of an integer
    too long for Python's int() (over 4,300 digits), and so are YAML aliases that stand for a
    structure without end or a hundred times the file's characters in values.
    """
    try:
        if kind == "json":
            return json.loads(text, object_pairs_hook=_unique_pairs(text))
        data = yaml.load(text, Loader=_UniqueKeyLoader)
    except RecursionError:
        if kind == "json":
            raise json.JSONDecodeError("nested too deeply", text, 0) from None
        raise yaml.YAMLError("nested too deeply") from None
    except ValueError as exc:
        if isinstance(exc, json.JSONDecodeError):
            raise
        # Python's int() refuses an integer of more than 4,300 digits, inside either parser.
        what = "a number of more digits than can be read" if "digits" in str(exc) else str(exc)
        if kind == "json":
            raise json.JSONDecodeError(what, text, 0) from None
        raise yaml.YAMLError(what) from None
    # An alias shares its anchor's value, so a few lines can stand for a structure without end
    # (an anchor inside itself: `a: &a [*a]`) or of 10⁹ values (aliases of aliases), which
    # every later walk over the values (key checks, validation) would follow for ever.
    if not _expands_within(data, _VALUES_PER_CHARACTER * len(text) + 1000):
        raise yaml.YAMLError(
            "its aliases stand for a structure without end or far larger than the file "
            "(an anchor used inside itself, or aliases of aliases)"
        )
    return data


# Values a YAML text may stand for through its aliases, per character: a config written out
# has fewer than one; a file that reuses a block by alias a few times stays far below this.
_VALUES_PER_CHARACTER = 100


def _expands_within(data: Any, budget: int) -> bool:
    """Whether ``data``, its shared values counted each time they occur, holds at most
    ``budget`` values (a cyclic structure holds infinitely many)."""
    stack, count = [data], 0
    while stack:
        item = stack.pop()
        count += 1
        if count > budget:
            return False
        if isinstance(item, dict):
            stack.extend(item.keys())
            stack.extend(item.values())
        elif isinstance(item, list | tuple):
            stack.extend(item)
    return True


def parse_structured(text: str, source: str | Path, kind: str | None = None) -> Any:
    """Parse ``text`` as JSON (``kind == "json"`` or a ``.json`` source) or else YAML.

    Raises
    ------
    ConfigError
        One line: ``source: not valid YAML: line L:C: problem``.
    """
    kind = kind or ("json" if Path(source).suffix.lower() == ".json" else "yaml")
    try:
        return load_structured(text, kind)
    except (json.JSONDecodeError, yaml.YAMLError) as exc:
        raise ConfigError(f"{source}: not valid {kind.upper()}: {parse_problem(exc)}") from None


def not_text(exc: UnicodeDecodeError) -> str:
    """``not UTF-8 text (byte 0xff at offset 0)``: the problem of a file that does not decode."""
    return f"not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at offset {exc.start})"


def not_a_file(path: Path) -> str | None:
    """Why ``path`` is not a regular file to read, or None when it is one (a pipe or device
    named as an input would block a read for ever)."""
    if path.is_file():
        return None
    if path.is_dir():
        return "a folder, not a file"
    if path.is_symlink() and not path.exists():
        return "a broken link"
    if path.exists():
        return "not a regular file (a pipe or a device?)"
    return "no such file"


def read_config_text(path: Path, what: str) -> str:
    """The UTF-8 text of a config-like file (``what``: ``"config"``, ``"the rectangle
    catalogue"``).

    Raises
    ------
    ConfigError
        ``path: cannot read WHAT: problem``: not a regular file, refused by the system, or
        not UTF-8 text.
    """
    problem = not_a_file(path)
    try:
        if problem is None:
            return path.read_text()
    except OSError as exc:
        problem = exc.strerror or str(exc)
    except UnicodeDecodeError as exc:
        problem = not_text(exc)
    raise ConfigError(f"{path}: cannot read {what}: {problem}") from None
