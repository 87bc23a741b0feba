"""Traveler log reader (on a small file written here), geometry, and the real trial (skipped without it)."""

import math
import pathlib

import numpy as np
import pytest
import torch

from irft_torch.hardware.traveler import TRAVELER_LEG, TravelerLogError, read_traveler_log

DATA = pathlib.Path(__file__).resolve().parents[3] / "shared" / "data" / "traveler_leg"
TRIAL = DATA / "traveler_trial_2024-02-02.csv"
needs_data = pytest.mark.skipif(not TRIAL.is_file(),
                                reason=f"Traveler trial not found at {TRIAL} (not shipped: no licence)")

HEADER = ("time,toeforce_x,toeforce_y,toe_position_x,toe_position_y,toe_velocity_x,toe_velocity_y,"
          "position,position1,torque,torque1,theta command,length command,state flag,current")


def _controller_row(t, theta_c, g, u0, u1):
    """One row as the controller would write it, from its own formulas (lowerproxy.cpp, restated):
    motor angles pos0 = theta_c - g, pos1 = theta_c + g (theta_c from straight up, toward +x);
    L = sqrt(l2^2 - (l1 sin g)^2) + l1 cos g + l3; toe (L sin theta_c, L cos theta_c)."""
    l1, l2, l3 = 0.1, 0.2, 0.05
    L = math.sqrt(l2**2 - (l1 * math.sin(g)) ** 2) + l1 * math.cos(g) + l3
    pos0, pos1 = theta_c - g, theta_c + g
    return [t, 0.0, 0.0, L * math.sin(theta_c), L * math.cos(theta_c), 0, 0, pos0, pos1, u0, u1, 0, 0, 1, 0]


def _write(path, rows, protocol="a,ground_height\n1,7,22.3\n"):
    path.write_text(protocol + HEADER + "\n" + "\n".join(",".join(repr(float(v)) for v in r) for r in rows) + "\n\n")
    return path


def test_reader_on_a_small_file(tmp_path):
    rows = [_controller_row(0.001 * i, math.pi + 0.1 * i, 1.2, 0.1, -0.2) for i in range(4)]
    log = read_traveler_log(_write(tmp_path / "trial.csv", rows))
    assert len(log) == 4 and log.columns[0] == "time" and log.columns[-1] == "current"
    # one more value than names: names align from the right, the extra is kept unnamed
    assert log.protocol == {"unnamed_0": 1.0, "a": 7.0, "ground_height": 22.3}
    assert log.ground_height == pytest.approx(0.223)
    np.testing.assert_allclose(log["state flag"], 1.0)
    np.testing.assert_allclose(log.time, [0, 0.001, 0.002, 0.003])


def test_reader_errors_name_the_line(tmp_path):
    rows = [_controller_row(0.0, math.pi, 1.2, 0.0, 0.0)]
    p = _write(tmp_path / "bad.csv", rows)
    p.write_text(p.read_text() + "0.1,2,3\n")  # line 5 is blank (skipped), line 6 is short
    with pytest.raises(TravelerLogError, match="line 6: 3 values, expected 15"):
        read_traveler_log(p)
    p.write_text("a,b\n1\n" + HEADER + "\n")
    with pytest.raises(TravelerLogError, match="line 2: 1 protocol values for 2 names"):
        read_traveler_log(p)
    p.write_text("a\n1\n" + HEADER + "\n" + ",".join(["x"] * 15) + "\n")
    with pytest.raises(TravelerLogError, match="line 4: not all numbers"):
        read_traveler_log(p)
    with pytest.raises(FileNotFoundError, match="no Traveler log"):
        read_traveler_log(tmp_path / "nope.csv")


def test_geometry_reproduces_the_controllers_toe_position(tmp_path):
    """Closed form: the Traveler's toe is (L + l3)(sin th, -cos th) with L the five-bar's leg length;
    with q = pi - position the package's kinematics give the controller's toe position."""
    rows = [_controller_row(0.0, math.pi + th, g, 0, 0) for th, g in [(0.0, math.pi / 2), (0.2, 1.0), (-0.3, 1.9)]]
    log = read_traveler_log(_write(tmp_path / "t.csv", rows))
    torch.testing.assert_close(TRAVELER_LEG.forward_kinematics(log.joint_angles()), log.toe_position())
    assert TRAVELER_LEG.forward_kinematics(torch.tensor([math.pi / 2, -math.pi / 2]))[1].item() == \
        pytest.approx(-(math.sqrt(0.2**2 - 0.1**2) + 0.05))


def test_statics_sign_on_a_constructed_load(tmp_path):
    """Torques that hold the leg against a known ground force, written the way the log stores them
    (tau = (-torque, torque1)), come back as that force."""
    q = torch.tensor([[math.pi / 2 + 0.1, -math.pi / 2 + 0.1]], dtype=torch.float64)
    F = torch.tensor([[0.5, 6.0]], dtype=torch.float64)  # sand pushing the toe up
    tau = TRAVELER_LEG.holding_torques(q, F)[0]
    pos = (math.pi - q[0]).tolist()
    row = [0.0, 0, 0, 0, 0, 0, 0, pos[0], pos[1], -tau[0].item(), tau[1].item(), 0, 0, 1, 0]
    log = read_traveler_log(_write(tmp_path / "s.csv", [row]))
    torch.testing.assert_close(log.ground_force()[0], F)


@needs_data
def test_real_trial_statics_and_sign():
    log = read_traveler_log(TRIAL)
    assert len(log) == 8592 and log.ground_height == pytest.approx(0.223)
    torch.testing.assert_close(TRAVELER_LEG.forward_kinematics(log.joint_angles()), log.toe_position(),
                               atol=1e-6, rtol=0)
    F, valid = log.ground_force()
    assert bool(valid.all())
    rms = (F - log.controller_ground_force()).pow(2).mean(0).sqrt()
    assert (rms < 1e-5).all()  # the controller's toeforce is (F_x, -F_z): float32 round-off apart
    z = log.toe_position()[:, 1]
    time = torch.as_tensor(log.time)  # one kind of mask: a torch bool tensor
    at_rest_in_air = (time > 1.0) & (time < 2.5)
    deep_hold = (z < -0.259) & (time > 4.0) & (time < 5.5)
    assert F[at_rest_in_air, 1].mean() < 0  # the links' weight pulls the toe down
    assert F[deep_hold, 1].mean() > F[at_rest_in_air, 1].mean() + 3  # the sand pushes it up
