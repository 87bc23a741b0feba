"""The data readers pointed at the wrong thing name it (was: scipy's or NumPy's error without the file
name), and a slip angle no run has is said (was: an empty list). Files made here: no data needed."""

import pytest

from irft_torch.data import dem, wheel


def test_dem_reader_names_a_file_that_is_not_its_csv(tmp_path):
    (tmp_path / "beta_30_plate_forces.csv").write_bytes(bytes(range(256)) * 4)
    (tmp_path / "beta_30_plate_positions.csv").write_text("0,30\n0,1,2,3,4\n")
    with pytest.raises(ValueError, match=r"beta_30_plate_forces.csv: not a text CSV file .* DEM plate file"):
        dem.read_runs(tmp_path)
    (tmp_path / "beta_30_plate_forces.csv").write_text("time,fx,fy,fz\nhello\n")
    with pytest.raises(ValueError, match=r"beta_30_plate_forces.csv: no run in it"):
        dem.read_runs(tmp_path)
    with pytest.raises(NotADirectoryError, match="is a file: read_runs takes the folder"):
        dem.read_runs(tmp_path / "beta_30_plate_forces.csv")


def test_wheel_readers_name_a_file_that_is_not_matlab(tmp_path):
    for name in ("all_smooth_data_2.mat", "smoothRFT.mat", "smooth_wheel_125_2D.mat", "smooth_wheel_125.mat"):
        (tmp_path / name).write_text("not a MATLAB file\n")
    for read in (lambda: wheel.read_wheel_runs(tmp_path, "smooth"), lambda: wheel.read_profile(tmp_path, "smooth"),
                 lambda: wheel.read_wheel_mesh(tmp_path, "smooth")):
        with pytest.raises(ValueError, match=r"\.mat: not a readable MATLAB \.mat file"):
            read()
    with pytest.raises(NotADirectoryError, match="is a file: give the folder that holds the rover-wheel data"):
        wheel.read_wheel_runs(tmp_path / "smoothRFT.mat", "smooth")


def test_a_slip_angle_no_run_has_is_said(tmp_path):
    """Two hand-made runs at 0 and 15 degrees (scipy writes the struct arrays): 7 degrees names both."""
    import numpy as np
    from scipy.io import savemat

    fields = ("beta", "slip", "Vry", "trial_num", "avg_Vx", "avg_Vry", "avg_Z", "avg_Fy", "avg_Fz", "std_Fy",
              "std_Fz", "avg_Fx")
    runs = np.zeros((1, 2), dtype=[(f, "O") for f in fields])
    rft = np.zeros((1, 2), dtype=[(f, "O") for f in ("beta", "slip", "ForceX", "ForceY", "ForceZ")])
    for i, angle in enumerate((0.0, 15.0)):
        for f in fields:
            runs[0, i][f] = np.array([[angle if f == "beta" else 1.0]])
        for f in ("beta", "slip", "ForceX", "ForceY", "ForceZ"):
            rft[0, i][f] = np.array([[angle if f == "beta" else 1.0]])
    savemat(tmp_path / "all_smooth_data_2.mat", {"all_results": runs})
    savemat(tmp_path / "smoothRFT.mat", {"RFToutput": rft})
    assert [r.slip_angle_deg for r in wheel.read_wheel_runs(tmp_path, "smooth", 15.0)] == [15.0]
    with pytest.raises(ValueError, match=r"no smooth run at slip angle 7 deg: all_smooth_data_2.mat holds slip angles "
                                         r"0, 15 deg"):
        wheel.read_wheel_runs(tmp_path, "smooth", 7.0)
