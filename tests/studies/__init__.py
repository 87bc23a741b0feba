"""Tests of the studies (``irft_torch.studies``) and of the experiment scripts behind them."""

import importlib.util
import pathlib
import sys

ROOT = pathlib.Path(__file__).resolve().parents[2]


def experiment(name: str):
    """experiments/<name>.py as a module (registered in ``sys.modules`` under ``name``, as its own imports expect)."""
    spec = importlib.util.spec_from_file_location(name, ROOT / "experiments" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod
