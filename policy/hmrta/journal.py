"""The board's journal file (``hmrta-journal/1``): one JSON line per published board version,
after a header line naming the mission; appended, flushed and fsynced by :class:`Journal`, read
back by :func:`read_journal` (a torn last line is dropped). :class:`hmrta.board.MissionBoard`
writes it and replays it on a restart (docs/semantics.md)."""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from .instance import Instance

JOURNAL_FORMAT = "hmrta-journal/1"
# how every journal file begins (hmrta.board.MissionBoard._mission_header)
JOURNAL_START = b'{"format":"' + JOURNAL_FORMAT.encode() + b'"'


class JournalError(ValueError):
    """A journal that cannot be replayed (written for another mission, or corrupt before its last
    line); one line naming the file and line."""


def instance_digest(inst: Instance) -> str:
    """The mission's ``instance_sha256``, as a solution records it (:attr:`Instance.fingerprint`:
    the mission, its timed events and the robots they add): a journal is replayed only on its own
    mission."""
    return inst.fingerprint


def read_journal(path: str | os.PathLike) -> tuple[dict[str, Any] | None, list[dict[str, Any]], int, str | None]:
    """-> (header or None, version lines, byte length of the intact part, why the tail was dropped
    or None). A last line that is cut short (no newline) or is not a JSON object is torn: it is
    left out; any earlier line that is not a JSON object is a :class:`JournalError`, and so is a
    file with no intact header that is not a header cut short (another file: the board would
    truncate it)."""
    p = Path(path)
    data = p.read_bytes() if p.exists() else b""
    lines = data.split(b"\n")
    tail = lines.pop()  # after the last newline: empty unless the last write was cut short
    good = len(data) - len(tail)
    dropped = f"a torn last line ({len(tail)} bytes without a newline)" if tail else None
    records: list[dict[str, Any]] = []
    for i, raw in enumerate(lines):
        try:
            rec = json.loads(raw)
            if not isinstance(rec, dict):
                raise ValueError("not a JSON object")
        except ValueError:  # JSONDecodeError and UnicodeDecodeError included
            if i == len(lines) - 1 and dropped is None:
                good -= len(raw) + 1
                dropped = f"a torn last line ({len(raw)} bytes that are not a JSON object)"
                break
            raise JournalError(f"{p}: line {i + 1} is not a JSON object (the journal is corrupt)") from None
        records.append(rec)
    header = None
    if not records and data and not data.startswith(JOURNAL_START[:len(data)]):
        # nothing intact and not the start of a header cut short: some other file, never truncated
        raise JournalError(f"{p}: not an hmrta journal (line 1 is not an {JOURNAL_FORMAT} header); "
                           f"refusing to overwrite it: name another journal file")
    if records:
        header = records.pop(0)
        if header.get("format") != JOURNAL_FORMAT:
            raise JournalError(f"{p}: line 1: expected format {JOURNAL_FORMAT!r}, got {header.get('format')!r}")
    return header, records, good, dropped


def journal_header(path: str | os.PathLike) -> dict[str, Any] | None:
    """The header of the journal at ``path`` (its first line) without reading the versions after
    it; None when there is no such file or its first line is no intact header (:func:`read_journal`,
    which a board resuming it runs, says what is wrong)."""
    try:
        with open(path, "rb") as f:
            first = f.readline()
        header = json.loads(first) if first.endswith(b"\n") else None
    except (OSError, ValueError):
        return None
    return header if isinstance(header, dict) and header.get("format") == JOURNAL_FORMAT else None


class Journal:
    """Append-only JSON lines; :meth:`append` writes one line, flushes it and (``sync``) fsyncs."""

    def __init__(self, path: str | os.PathLike, keep: int):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        os.ftruncate(fd, keep)  # a torn tail is dropped before anything is appended
        os.lseek(fd, keep, os.SEEK_SET)
        self.fh = os.fdopen(fd, "ab")
        self.lines = 0

    def append(self, rec: dict[str, Any], sync: bool) -> None:
        self.fh.write((json.dumps(rec, separators=(",", ":"), allow_nan=False) + "\n").encode())
        self.fh.flush()
        if sync:
            os.fsync(self.fh.fileno())
        self.lines += 1

    def close(self) -> None:
        self.fh.close()
