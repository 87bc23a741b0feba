"""Tests of the studies (``irft_torch.studies``) and of the experiment scripts behind them."""

import importlib.util
import pathlib
import sys

ROOT = pathlib.Path(__file__).resolve().parents[2]


def experiment_path(name: str) -> pathlib.Path:
    """experiments/<group>/<name>.py (the scripts are grouped: validation, calibration, benchmarks)."""
    found = sorted((ROOT / "experiments").glob(f"*/{name}.py"))
    if len(found) != 1:
        raise FileNotFoundError(f"experiments/*/{name}.py: found {found}")
    return found[0]


def experiment(name: str):
    """experiments/<name>.py as a module (registered in ``sys.modules`` under ``name``, as its own imports expect)."""
    spec = importlib.util.spec_from_file_location(name, experiment_path(name))
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod
