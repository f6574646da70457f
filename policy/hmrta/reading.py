"""Guarded readers for every file the command line takes (instances, CTAS-D configs, routes,
solutions, training configs).

One reader for all text inputs: the path must be a regular file (a folder, FIFO or device is
refused before it is opened, so nothing blocks) of at most :data:`MAX_BYTES`, holding UTF-8 text.
JSON and YAML are parsed safely: YAML with the safe constructors only, duplicate keys refused,
aliases allowed to add at most :data:`MAX_ALIAS_NODES` nodes to the document (an alias bomb is
refused before anything walks it) and no recursive aliases; both formats at most
:data:`MAX_DEPTH` levels deep, and integers of more than 4300 digits are refused.

Every problem raises the caller's error class (a ``ValueError`` subclass, :class:`InputError` by
default) with one line that names the file and, where the content is at fault, the line.
:func:`short` is the bounded ``repr`` that messages about file contents use.
"""
from __future__ import annotations

import json
import math
import os
import re
import reprlib
import stat
import sys
from pathlib import Path
from typing import Any

import yaml

MAX_BYTES = 64 * 2**20  # largest input file read
MAX_DEPTH = 32  # deepest nesting of lists / mappings in a JSON or YAML input
MAX_ALIAS_NODES = 100_000  # nodes that YAML aliases may add to a document when expanded


class InputError(ValueError):
    """An unreadable or malformed input file (a user error; one line naming the file)."""


# ---------------------------------------------------------------------------------------------
# messages
# ---------------------------------------------------------------------------------------------
class _ShortRepr(reprlib.Repr):
    def __init__(self) -> None:
        super().__init__()
        self.maxlevel, self.maxlist, self.maxdict, self.maxtuple, self.maxset = 2, 4, 4, 4, 4
        self.maxstring, self.maxother, self.maxlong = 40, 40, 40

    def repr_int(self, x: int, level: int) -> str:
        if x.bit_length() > 128:  # also avoids Python's limit on int -> str conversion
            return f"<an integer of about {int(x.bit_length() * 0.30103)} digits>"
        return super().repr_int(x, level)

    def repr_Tensor(self, x: Any, level: int) -> str:  # torch tensors (checkpoints): shape, not values
        return f"<tensor of shape {list(x.shape)}, {str(x.dtype).replace('torch.', '')}>"


_SHORT = _ShortRepr()


def short(v: Any) -> str:
    """``repr`` on one line, bounded in length and depth (safe on huge, deep or self-referencing
    values)."""
    try:
        r = one_line(_SHORT.repr(v))
    except Exception:  # noqa: BLE001 - a value whose repr fails is still reported
        return f"<{type(v).__name__}>"
    return r if len(r) <= 160 else r[:157] + "..."


def one_line(text: str) -> str:
    return " ".join(str(text).split())


# ---------------------------------------------------------------------------------------------
# files
# ---------------------------------------------------------------------------------------------
def read_bytes(path: str | Path, error: type[Exception] = InputError, max_bytes: int = MAX_BYTES) -> bytes:
    """The bytes of a regular file; a missing path, a folder or a special file is an error."""
    p = Path(path)
    try:
        st = os.stat(p)
    except FileNotFoundError:
        raise error(f"{p}: no such file") from None
    except OSError as e:
        raise error(f"{p}: cannot read ({e.strerror or type(e).__name__})") from None
    except ValueError as e:  # e.g. an embedded NUL byte in the path
        raise error(f"{p}: invalid path ({e})") from None
    if stat.S_ISDIR(st.st_mode):
        raise error(f"{p}: is a folder, expected a file")
    if not stat.S_ISREG(st.st_mode):
        raise error(f"{p}: not a regular file")
    if st.st_size > max_bytes:
        raise error(f"{p}: too large ({st.st_size} bytes; at most {max_bytes})")
    try:
        with open(p, "rb") as f:
            data = f.read(max_bytes + 1)
    except OSError as e:
        raise error(f"{p}: cannot read ({e.strerror or type(e).__name__})") from None
    if len(data) > max_bytes:
        raise error(f"{p}: too large (more than {max_bytes} bytes)")
    return data


def decode_text(data: bytes, source: str, error: type[Exception] = InputError) -> str:
    """Strict UTF-8 (a leading byte-order mark is dropped)."""
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise error(f"{source}: not UTF-8 text (byte offset {e.start})") from None
    return text[1:] if text.startswith("\ufeff") else text


def read_text(path: str | Path, error: type[Exception] = InputError) -> str:
    return decode_text(read_bytes(path, error), str(path), error)


# ---------------------------------------------------------------------------------------------
# JSON
# ---------------------------------------------------------------------------------------------
class _DuplicateKey(Exception):
    pass


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict:
    """An object whose every key is written once (json's default keeps the last silently)."""
    out = dict(pairs)
    if len(out) != len(pairs):
        seen: set[str] = set()
        for k, _ in pairs:
            if k in seen:
                raise _DuplicateKey(k)
            seen.add(k)
    return out


def _too_long(e: Exception) -> str | None:
    """What is wrong, in the file's terms, when ``e`` is Python's refusal of an integer written
    with too many digits (its message advises a call the user cannot make); else None."""
    if isinstance(e, ValueError) and "Exceeds the limit" in str(e) and "digits" in str(e):
        return f"an integer of more than {sys.get_int_max_str_digits()} digits"
    return None


def parse_json(text: str, source: str, error: type[Exception] = InputError) -> Any:
    try:
        data = json.loads(text, object_pairs_hook=_unique_keys)
    except _DuplicateKey as e:
        raise error(f"{source}: invalid JSON (duplicate key {short(e.args[0])} in one object: "
                    "the last would silently win)") from None
    except json.JSONDecodeError as e:
        raise error(f"{source}:{e.lineno}: invalid JSON ({e.msg})") from None
    except RecursionError:
        raise error(f"{source}: invalid JSON (nested more than {MAX_DEPTH} levels deep)") from None
    except ValueError as e:  # an integer beyond Python's int-from-text limit
        raise error(f"{source}: invalid JSON ({_too_long(e) or one_line(e)})") from None
    _check_shape(data, source, "JSON", error)
    return data


def read_json(path: str | Path, error: type[Exception] = InputError) -> Any:
    return parse_json(read_text(path, error), str(path), error)


# ---------------------------------------------------------------------------------------------
# YAML
# ---------------------------------------------------------------------------------------------
class SafeStrictLoader(yaml.SafeLoader):
    """SafeLoader that refuses a key written twice in one mapping (the last would silently win)
    and documents nested deeper than :data:`MAX_DEPTH` (checked while composing, before any
    recursion can run out of stack)."""

    _depth = 0

    def compose_node(self, parent, index):  # type: ignore[override]
        self._depth += 1
        try:
            if self._depth > MAX_DEPTH:
                mark = self.peek_event().start_mark
                raise yaml.composer.ComposerError(
                    None, None, f"nested more than {MAX_DEPTH} levels deep", mark)
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1


def _no_duplicates(loader: yaml.SafeLoader, node: yaml.MappingNode, deep: bool = False):
    seen: dict = {}
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        try:
            hash(key)
        except TypeError:
            raise yaml.constructor.ConstructorError(
                None, None, f"a mapping key must be a scalar, not a {type(key).__name__}",
                key_node.start_mark) from None
        if key in seen:
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key {short(key)} (first on line {seen[key] + 1})", key_node.start_mark)
        seen[key] = key_node.start_mark.line
    return loader.construct_mapping(node, deep)


SafeStrictLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _no_duplicates)
# YAML 1.1 (PyYAML) reads 2e-1 or 1e3 (an exponent without a decimal point) as a string; YAML 1.2 and
# every other reader of these files read a number
SafeStrictLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float", re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"))


def _alias_growth(root: yaml.Node | None) -> int:
    """Nodes that aliases add when the document is expanded (shared nodes counted per use);
    -1 for a node that contains itself. Iterative, linear in the distinct nodes."""
    if root is None:
        return 0
    size: dict[int, int] = {}  # expanded size of each finished node
    active: set[int] = set()
    distinct = 0
    stack: list[tuple[yaml.Node, bool]] = [(root, False)]
    while stack:
        node, done = stack.pop()
        nid = id(node)
        if done:
            active.discard(nid)
            kids = _children(node)
            size[nid] = 1 + sum(size[id(k)] for k in kids)
            continue
        if nid in size:
            continue
        if nid in active:
            return -1
        active.add(nid)
        distinct += 1
        stack.append((node, True))
        for k in _children(node):
            if id(k) in active:
                return -1
            if id(k) not in size:
                stack.append((k, False))
    return size[id(root)] - distinct


def _children(node: yaml.Node) -> list[yaml.Node]:
    if isinstance(node, yaml.SequenceNode):
        return list(node.value)
    if isinstance(node, yaml.MappingNode):
        return [n for kv in node.value for n in kv]
    return []


def parse_yaml(text: str, source: str, error: type[Exception] = InputError) -> Any:
    loader = None
    try:
        loader = SafeStrictLoader(text)
        node = loader.get_single_node()
        growth = _alias_growth(node)
        if growth < 0:
            raise error(f"{source}: invalid YAML (an alias refers to a node that contains it)")
        if growth > MAX_ALIAS_NODES:
            raise error(f"{source}: invalid YAML (aliases expand the document by {growth} nodes; "
                        f"at most {MAX_ALIAS_NODES} are allowed)")
        data = loader.construct_document(node) if node is not None else None
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        line = f":{mark.line + 1}" if mark is not None else ""
        problem = getattr(e, "problem", None) or str(e)
        raise error(f"{source}{line}: invalid YAML ({one_line(problem)})") from None
    except RecursionError:
        raise error(f"{source}: invalid YAML (nested more than {MAX_DEPTH} levels deep)") from None
    except error:
        raise
    except Exception as e:  # noqa: BLE001 - an integer beyond Python's int-from-text limit, a date
        # out of range, or a PyYAML constructor failing on a malformed scalar (e.g. `!!timestamp 99999-01-01`)
        raise error(f"{source}: invalid YAML ({_too_long(e) or f'{type(e).__name__}: {one_line(e)[:200]}'})") from None
    finally:
        if loader is not None:
            loader.dispose()
    _check_shape(data, source, "YAML", error)
    return data


def read_yaml(path: str | Path, error: type[Exception] = InputError) -> Any:
    return parse_yaml(read_text(path, error), str(path), error)


def _check_shape(data: Any, source: str, kind: str, error: type[Exception]) -> None:
    """Depth limit on parsed data (iterative; YAML's shared values are walked once per use, which
    the alias limit bounds)."""
    stack = [(data, 1)]
    while stack:
        v, d = stack.pop()
        if isinstance(v, (list, dict)):
            if d > MAX_DEPTH:
                raise error(f"{source}: invalid {kind} (nested more than {MAX_DEPTH} levels deep)")
            stack.extend((x, d + 1) for x in (v.values() if isinstance(v, dict) else v))


def finite(v: Any) -> bool:
    """A real number (not bool) that is finite, also for integers too large for a float."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return False
    try:
        return math.isfinite(float(v))
    except OverflowError:
        return False
