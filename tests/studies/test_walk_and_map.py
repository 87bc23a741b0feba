"""The walk-and-map experiment's baselines against hand values (``experiments/validation/walk_and_map.py``)."""

import importlib.util
import sys

import torch

from . import experiment_path


def _script():
    spec = importlib.util.spec_from_file_location("walk_and_map", experiment_path("walk_and_map"))
    mod = importlib.util.module_from_spec(spec)
    sys.modules["walk_and_map"] = mod
    spec.loader.exec_module(mod)
    return mod


def test_scalar_baseline_recovers_a_known_scale_of_the_generic_map_everywhere():
    """On a bed of Li et al.'s generic map scaled by 1.3 (no noise), each stance's least-squares scale is 1.3 and
    the GP over the footholds predicts 1.3 at places between them."""
    from irft_torch.rft import FourierStressMap, TerrainField

    wm = _script()
    field = TerrainField.uniform(FourierStressMap.generic(1.3, 1.3))
    c, F, s, stance, feet = wm.walk_over(field, 8, seed=0, noise=0.0)
    k = wm.scalar_gp(c, F, stance, feet, torch.tensor([[0.5, 0.1], [2.2, -0.1]], dtype=torch.float64))
    torch.testing.assert_close(k, torch.full((2,), 1.3, dtype=torch.float64), rtol=2e-3, atol=0)


def test_walk_places_every_sample_near_its_foothold_and_seen_angles_cover_the_strokes():
    from irft_torch.rft import FourierStressMap, TerrainField

    wm = _script()
    c, F, s, stance, feet = wm.walk_over(TerrainField.uniform(FourierStressMap.generic()), 6, seed=1)
    assert len(c) == len(F) == len(s) == len(stance) and stance.max() == 5
    drift = (s - feet[stance]).norm(dim=-1)
    assert float(drift.max()) < 0.1  # a stroke drags 6 cm at most
    b, g = wm.grid()
    seen = wm.seen_angles(c, b, g)
    assert 0.2 < float(seen.double().mean()) < 1.0  # some of the square, not all of it
