"""The ``irft`` command: its parser (one subcommand per module of this package) and ``main``.

torch (and so rft, gp, hardware) is imported where a command needs it, not here: parsing, --help and
the start of ``irft reproduce``'s worker processes come first (see ``main``).
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings

from . import fit, ingest, live, record, reproduce, simulate
from .arguments import _validate, warn

__all__ = ["build_parser", "main"]

COMMANDS = (simulate, reproduce, record, ingest, fit, live)  # in the order ``irft --help`` lists them


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors: 'irft CMD: error: argument --x: ... (see irft CMD --help)'."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _one_line(command: str):
    """A ``warnings.showwarning`` that prints each warning as ``warn`` does."""

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        warn(command, message)

    return show


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="irft", description="Inverse Resistive Force Theory tools.")
    sub = parser.add_subparsers(dest="command", required=True)
    for command in COMMANDS:
        command.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the ``irft`` command. A user error (bad value, missing or damaged file, no device) prints one
    line naming the argument or file and returns non-zero, never a traceback (IRFT_DEBUG=1 shows one)."""
    parser = build_parser()
    a = parser.parse_args(argv)
    if a.command == "reproduce":  # with worker processes, their imports run beside this process's
        from ..studies.workers import default_workers, start_worker_server

        if (a.jobs or default_workers()) > 1:
            start_worker_server(reproduce.PRELOAD)
    import torch

    torch.set_default_dtype(torch.float64)
    debug = os.environ.get("IRFT_DEBUG") == "1"
    try:
        with warnings.catch_warnings():
            if not debug:  # one line per warning, 'irft CMD: warning: ...', not Python's file/line/source format
                warnings.showwarning = _one_line(a.command)
            _validate(a)
            return a.func(a)
    except KeyboardInterrupt:
        print(f"irft {a.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as e:  # noqa: BLE001 - reported as one line; IRFT_DEBUG=1 re-raises
        if debug:
            raise
        import can

        user = isinstance(e, (ValueError, OSError, can.CanError, EOFError, KeyError))
        text = " ".join(str(e).split()) or type(e).__name__
        if not user:
            kind = type(e).__qualname__ if type(e).__module__ == "builtins" else \
                f"{type(e).__module__}.{type(e).__qualname__}"
            text = (f"{kind}: {text} (unexpected: if your input looks right, rerun with IRFT_DEBUG=1 and "
                    "report the traceback)")
        print(f"irft {a.command}: error: {text}", file=sys.stderr)
        return 2 if user else 3
