"""The DEM plate-intrusion reader and its angle mapping (skipped where the shared data are absent)."""

import math
import pathlib

import numpy as np
import pytest
import torch

from irft_torch import dem_data as D
from irft_torch.rft import FourierStressMap

DATA = pathlib.Path(__file__).resolve().parents[2] / "shared" / "data" / "dem_plate_intrusion"
needs_data = pytest.mark.skipif(not DATA.is_dir(), reason=f"DEM data not found at {DATA} (not shipped: no licence)")


def write(path, text):
    path.write_text(text)
    return path


def test_reader_quirks_on_a_hand_made_file(tmp_path):
    write(tmp_path / "beta_30_plate_forces.csv",
          "90,30,,\n0,0,0,0\n0.001,1.5e-01,0,2E+00\n0.002,0.2,0,2.5,\n0.003,0.3,0\n"  # truncated last row
          "81,30\n0,0,0,0\n0.001,0.1,0,1\nbad,row,x,y\n")
    write(tmp_path / "beta_30_plate_positions.csv",
          "90,30,,,\n0,0,0,15,9\n0.001,0,0,14.9,9\n0.002,0,0,14.8,9\n0.003,0,0,14.7,9\n"
          "81,30,,,\n0,0,0,15,9\n0.001,0,0,14.9,9\n")
    runs, rep = D.read_runs(tmp_path)
    assert [(r.gamma_deg, len(r.t)) for r in runs] == [(81.0, 2), (90.0, 3)]
    r90 = runs[1]
    np.testing.assert_allclose(r90.force[1], [0.15, 0.0, 2.0])  # scientific notation, trailing comma
    reasons = {x[2] for x in rep.skipped_rows}
    assert "3 values, expected 4" in reasons and "not numbers" in reasons
    assert ("beta 30, gamma 90", 0, 1) in rep.unmatched  # t = 3 ms: its force row was truncated
    assert "unparseable" in rep.summary()
    with pytest.raises(FileNotFoundError, match="no DEM data directory"):
        D.read_runs(tmp_path / "nope")


def test_contacts_of_a_tilted_plate_by_hand():
    run = D.DEMRun(30.0, 90.0, np.array([0.0, 0.1]), np.array([[1.0, 0, 2.0], [1.0, 0, 2.0]]),
                   np.array([[0, 0, 5.0], [0, 0, 4.0]]), np.array([9.0, 9.0]))
    c, f = D.run_contacts(run, n_segments=2)
    # segment centres at s = -/+ 3.81/4 along a plate tilted by -30 deg (DESIGN): z = zc -/+ s sin(-30)
    s = 3.81 / 4
    depth0 = np.array([9 - (5 + s * 0.5), 9 - (5 - s * 0.5)])
    area = 3.81 / 2 * 2.54
    torch.testing.assert_close(c.weight_z[0], torch.tensor(depth0 * area))
    assert c.beta[0, 0].item() == pytest.approx(math.radians(30)) and c.gamma[0, 0].item() == pytest.approx(math.pi / 2)
    assert (c.weight_x == c.weight_z).all()  # motion toward -x: the x contribution flips sign
    torch.testing.assert_close(f[0], torch.tensor([1.0, 2.0], dtype=torch.float64))


@needs_data
def test_real_data_mapping_correlates_with_the_generic_map():
    runs, rep = D.read_runs(DATA)
    runs = [r for r in runs if r.gamma_deg >= 45]
    assert len(runs) == 48
    gen = FourierStressMap.generic()
    meas = np.array([D.run_stress(r) for r in runs])
    pred = np.array([gen(*map(torch.tensor, D._canonical(r))).tolist() for r in runs])
    corr = [np.corrcoef(meas[:, k], pred[:, k])[0, 1] for k in range(2)]
    assert corr[0] > 0.94 and corr[1] > 0.93, corr  # README: about 0.95 for both axes
    # the other tilt sign would be wrong: x correlation collapses
    D.TILT_SIGN, old = 1.0, D.TILT_SIGN
    try:
        wrong = np.array([gen(*map(torch.tensor, D._canonical(r))).tolist() for r in runs])
    finally:
        D.TILT_SIGN = old
    assert np.corrcoef(meas[:, 0], wrong[:, 0])[0, 1] < 0.5
