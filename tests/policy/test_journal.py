"""The journal file on its own (hmrta.journal); the board's use of it (replay, resume, torn lines
under a running board) is tested in test_board.py."""
from __future__ import annotations

import json

import pytest

from hmrta.journal import JOURNAL_FORMAT, Journal, JournalError, journal_header, read_journal

HEADER = {"format": JOURNAL_FORMAT, "session": "s1", "instance_sha256": "ab"}


def _write(path, *lines: bytes) -> None:
    path.write_bytes(b"".join(lines))


def _line(rec: dict) -> bytes:
    return (json.dumps(rec, separators=(",", ":")) + "\n").encode()  # as the board writes them


def test_a_journal_reads_back_its_header_and_versions(tmp_path):
    j = tmp_path / "j.jsonl"
    _write(j, _line(HEADER), _line({"v": 1}), _line({"v": 2}))
    header, recs, good, dropped = read_journal(j)
    assert header == HEADER and recs == [{"v": 1}, {"v": 2}]
    assert good == j.stat().st_size and dropped is None
    assert journal_header(j) == HEADER


@pytest.mark.parametrize("tail,why", [(b'{"v": 3', "without a newline"), (b"[1, 2]\n", "not a JSON object")])
def test_a_torn_last_line_is_left_out_and_the_intact_length_given(tmp_path, tail, why):
    j = tmp_path / "j.jsonl"
    _write(j, _line(HEADER), _line({"v": 1}), tail)
    header, recs, good, dropped = read_journal(j)
    assert header == HEADER and recs == [{"v": 1}]
    assert good == j.stat().st_size - len(tail) and why in dropped


def test_a_corrupt_line_before_the_last_names_the_file_and_line(tmp_path):
    j = tmp_path / "j.jsonl"
    _write(j, _line(HEADER), b"not json\n", _line({"v": 2}))
    with pytest.raises(JournalError, match=r"j\.jsonl: line 2 is not a JSON object"):
        read_journal(j)


def test_another_file_is_refused_and_a_header_cut_short_is_not(tmp_path):
    other = tmp_path / "notes.txt"
    other.write_bytes(b"my notes\n")
    with pytest.raises(JournalError, match="not an hmrta journal"):
        read_journal(other)
    assert other.read_bytes() == b"my notes\n"
    cut = tmp_path / "cut.jsonl"
    cut.write_bytes(_line(HEADER)[:20])  # the first write cut short
    assert read_journal(cut) == (None, [], 0, "a torn last line (20 bytes without a newline)")
    assert journal_header(cut) is None and journal_header(tmp_path / "missing.jsonl") is None
    assert read_journal(tmp_path / "missing.jsonl") == (None, [], 0, None)


def test_a_header_of_another_format_is_refused(tmp_path):
    j = tmp_path / "j.jsonl"
    _write(j, _line({"format": "hmrta-journal/0"}))
    with pytest.raises(JournalError, match="line 1: expected format 'hmrta-journal/1'"):
        read_journal(j)
    assert journal_header(j) is None


def test_appending_drops_the_torn_tail_first(tmp_path):
    j = tmp_path / "sub" / "j.jsonl"
    j.parent.mkdir()
    _write(j, _line(HEADER), _line({"v": 1}), b'{"v": 2, "cut')
    _, _, good, _ = read_journal(j)
    out = Journal(j, keep=good)
    out.append({"v": 2}, sync=True)
    out.append({"v": 3}, sync=False)
    out.close()
    assert out.lines == 2
    header, recs, _, dropped = read_journal(j)
    assert header == HEADER and recs == [{"v": 1}, {"v": 2}, {"v": 3}] and dropped is None


def test_non_finite_numbers_are_never_written(tmp_path):
    out = Journal(tmp_path / "j.jsonl", keep=0)
    with pytest.raises(ValueError):
        out.append({"clock": float("nan")}, sync=False)
    out.close()
