"""The ``hmrta`` command line: one module per group of commands (``solving``, ``data``,
``benchmarking``, ``training``, ``rendering``), what they share (``common``, ``threads``,
``progress``) and the argument parser (``parser``); ``main`` runs a command.

User errors (bad files, options, checkpoints) exit 2 with a one-line message on stderr; internal
errors exit 1 with a traceback.
"""
from __future__ import annotations

import sys
import traceback

from .common import UserError, _user_errors, writable
from .parser import HelpFormatter, Parser, build_parser
from .progress import SolveProgress
from .threads import _threads, set_torch_threads

__all__ = ["main", "build_parser", "Parser", "HelpFormatter", "SolveProgress", "UserError", "writable",
           "set_torch_threads"]


class _PrintedOutput:
    """Standard output that goes quiet, and lets the command go on, once its reader has gone
    (``hmrta solve ... | head -1``): what a command writes to files is its result, what it prints
    is a summary, so a closed pipe must not cut a solve short or lose a file it was to write.
    Another failure to write it (a full disk) also lets the command go on, and is kept in
    ``failed`` to be reported once."""

    def __init__(self, stream):
        self._stream, self.reader_gone = stream, False
        self.failed: OSError | None = None

    def write(self, text: str) -> int:
        if not self.reader_gone:
            try:
                return self._stream.write(text)
            except BrokenPipeError:
                self._gone()
            except OSError as e:
                self.failed = e
                self._gone()
        return len(text)

    def flush(self) -> None:
        if not self.reader_gone:
            try:
                self._stream.flush()
            except BrokenPipeError:
                self._gone()
            except OSError as e:
                self.failed = e
                self._gone()

    def _gone(self) -> None:
        self.reader_gone = True
        try:  # what is still buffered, and the interpreter's last flush, go nowhere
            import os

            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, self._stream.fileno())
            os.close(devnull)
        except (OSError, ValueError, AttributeError):
            pass

    def __getattr__(self, name):
        return getattr(self._stream, name)


def main(argv: list[str] | None = None) -> int:
    stdout = sys.stdout
    sys.stdout = printed = _PrintedOutput(stdout)
    try:
        status = _main(argv)
        printed.flush()
    finally:
        sys.stdout = stdout
    if printed.failed is not None:  # what was to be printed is lost; files written with --out are whole
        print(f"hmrta: error: cannot write to standard output ({printed.failed.strerror or printed.failed})",
              file=sys.stderr)
        return status or 1
    return status


def _main(argv: list[str] | None) -> int:
    try:
        parser = build_parser()  # (imports the method table: a moment on a loaded machine)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    args = parser.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)  # for the provenance of results
    threads = None
    try:
        threads = _threads(args)
        return args.fn(args)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 0
    except Exception as e:  # noqa: BLE001
        from ..errors import caused_by_interrupt

        if isinstance(e, ImportError) and caused_by_interrupt(e):  # a Ctrl-C while an extension module loaded
            print("interrupted", file=sys.stderr)
            return 130
        if isinstance(e, _user_errors()):
            print(f"hmrta: error: {' '.join(str(e).splitlines())}", file=sys.stderr)  # always one line
            return 2
        traceback.print_exc()
        print(f"hmrta: internal error: {type(e).__name__}: {e}", file=sys.stderr)
        return 1
    finally:
        if threads is not None:
            threads.remove()
