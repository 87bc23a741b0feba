import os

import matplotlib
import pytest
import torch

matplotlib.use("Agg")
torch.set_num_threads(min(2, os.cpu_count() or 1))


@pytest.fixture(autouse=True)
def _float64_default():
    old = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(old)


def _fault_fuzz():
    """experiments/validation/fault_fuzz.py as a module (its simulated logs and edits serve the fault tests)."""
    import importlib.util
    import pathlib
    import sys

    if "fault_fuzz" not in sys.modules:
        path = pathlib.Path(__file__).resolve().parents[1] / "experiments" / "validation" / "fault_fuzz.py"
        spec = importlib.util.spec_from_file_location("fault_fuzz", path)
        mod = importlib.util.module_from_spec(spec)
        sys.modules["fault_fuzz"] = mod
        spec.loader.exec_module(mod)
    return sys.modules["fault_fuzz"]


@pytest.fixture(scope="session")
def fault_fuzz():
    return _fault_fuzz()


@pytest.fixture(scope="session")
def sim_logs(tmp_path_factory, fault_fuzz):
    """A simulated leg's clean logs in the known sand (generic map; fault_fuzz.base_logs): the candump
    lines [t, channel, rest] of a trial ("trial"), its run in air ("air") and another leg's trial in
    looser sand ("other"), all on channel can0; ``oracle(ds)`` is the largest |force - RFT of the
    dataset's own contacts| (N)."""
    from irft_torch import rft

    torch.set_default_dtype(torch.float64)
    base = fault_fuzz.base_logs(tmp_path_factory.mktemp("sim_logs"))
    generic = rft.FourierStressMap.generic()
    base["oracle"] = lambda ds: float((ds.forces - rft.forces(generic, ds.contacts)).abs().max())
    return base
