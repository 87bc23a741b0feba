"""The ``irft`` command (``irft_torch.cli:main``): one module per subcommand (``simulate``,
``reproduce``, ``record``, ``ingest``, ``fit``), the options and checks they share (``arguments``),
the parser and ``main`` (``command``). Every subcommand has ``--help``. Importing it does not
import torch."""

from .arguments import UsageError
from .command import build_parser, main

__all__ = ["main", "build_parser", "UsageError"]
