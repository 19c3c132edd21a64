"""What every hmpf command shares: ``--version``, one-line errors, a quiet Ctrl-C and pipe.

Each command's ``main(argv)`` parses its arguments, then hands its body to :func:`run`::

    def main(argv: list[str] | None = None) -> int:
        parser = build_parser()          # add_version(parser) inside
        args = parser.parse_args(argv)
        return run("hmpf-eval", lambda: _run(args))

``run`` turns an :class:`~hmpf.errors.HmpfError` into ``prog: error: message`` and exit 2,
Ctrl-C (``KeyboardInterrupt``) into one line and exit 130 (the shell's code for SIGINT), and
a closed pipe on stdout (``| head``) into a quiet exit 141; never a traceback.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable
from importlib import metadata

from hmpf.errors import HmpfError

__all__ = [
    "EXIT_BROKEN_PIPE",
    "EXIT_ERROR",
    "EXIT_INTERRUPTED",
    "add_version",
    "package_version",
    "run",
]

#: Exit status of a command that stopped on a user error (bad input, corrupt index, ...).
EXIT_ERROR = 2
#: Exit status when stdout's reader closed early (128 + SIGPIPE, as a shell reports it).
EXIT_BROKEN_PIPE = 141
#: Exit status after Ctrl-C: 128 + SIGINT, what a shell reports for an interrupted program.
EXIT_INTERRUPTED = 130


def package_version() -> str:
    """The installed distribution's version (``"unknown"`` when run from a bare checkout)."""
    try:
        return metadata.version("hmpf")
    except metadata.PackageNotFoundError:
        return "unknown"


def add_version(parser: argparse.ArgumentParser) -> None:
    """Add ``--version`` (prints ``prog hmpf X.Y.Z`` and exits 0) to a parser."""
    parser.add_argument(
        "--version", action="version", version=f"%(prog)s (hmpf {package_version()})"
    )


def run(prog: str, body: Callable[[], int], *, interrupted: str = "interrupted") -> int:
    """Run a command's body; map errors to one stderr line and an exit status.

    Args:
        prog: the command's name, the prefix of every message (``hmpf-index``).
        body: the command itself, returning its exit status.
        interrupted: what to say after Ctrl-C (e.g. that the index is untouched).

    Returns:
        ``body()``'s status, :data:`EXIT_ERROR` after an :class:`HmpfError`,
        :data:`EXIT_INTERRUPTED` after Ctrl-C, or :data:`EXIT_BROKEN_PIPE` when stdout's
        reader went away.
    """
    try:
        return body()
    except HmpfError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print(f"{prog}: {interrupted}", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:
        # The reader went away (`hmpf-index info | head`): stop quietly, and point stdout at
        # /dev/null so the interpreter's final flush does not raise again.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_BROKEN_PIPE
