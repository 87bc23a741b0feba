"""`irft ingest` against references written here, not against the package's own leg model.

The logs are built line by line in this file (candump text, CANSimple or MIT-mode bytes packed
here), from a prescribed toe path and a prescribed ground force; the joint angles come from the
closed-form inverse kinematics of the coaxial five-bar and the currents from its closed-form
statics (hardware_facts.md): L(g) = l1 cos g + sqrt(l2^2 - l1^2 sin^2 g), q1 = theta + g,
q2 = theta - g, F_radial = (tau1 - tau2) / L'(g), F_tangential = (tau1 + tau2) / L, ground force
= -(F_radial e_r + F_tangential e_t). A sign or convention error in the package's FiveBarLeg,
MotorModel or decoders cannot cancel out here.
"""

import math
import struct

import numpy as np
import pytest
import torch

from irft_torch.cli import main
from irft_torch.hardware import FiveBarLeg, load_dataset

from .closed_form import ik_coaxial, ik_spaced, torques_coaxial, torques_numeric

RATE = 100.0
T_END = 2.0
DEPTH = 0.03  # toe reference point below the surface, m


def force_at(t):
    """The prescribed ground force on the toe, N (any smooth function: ingest must return it)."""
    return (-2.0 - math.sin(math.pi * t), 12.0 + 3.0 * math.cos(math.pi * t))


def toe_at(t, reverse=False, hip_height=0.25):
    x = -0.10 + 0.20 * t / T_END
    return (-x if reverse else x), -DEPTH - hip_height


def candump(t, arb, data):
    return f"({t:.6f}) can0 {arb:03X}#{data.hex().upper()}"


def write_log(path, *, l1=0.15, l2=0.30, hip_height=0.25, kt=0.0973, directions=(1, 1), offsets=(0.0, 0.0),
              gear=1.0, spacing=0.0, nodes=(0, 1), reverse=False, t_end=T_END, protocol="odrive", t0=1.7e9,
              spike=None, torques=False):
    """Encoder and Get_Iq frames (or MIT replies) for the prescribed path and force, by hand."""
    lines = []
    n = int(round(t_end * RATE)) + 1
    for k in range(n):
        t = k / RATE
        x, z = toe_at(t, reverse, hip_height)
        F = force_at(t)
        if spacing:
            ik = lambda x_, z_: ik_spaced(x_, z_, l1, l2, spacing)  # noqa: E731
            q, tau = ik(x, z), torques_numeric(x, z, F, ik)
        else:
            q, tau = ik_coaxial(x, z, l1, l2), torques_coaxial(x, z, F, l1, l2)
        for i, node in enumerate(nodes):
            d = directions[i]
            if protocol == "mit":  # AK80-9: P +-12.5 rad, V +-50 rad/s, T +-18 N m (output side)
                pu = int((d * (q[i] - offsets[i]) + 12.5) * 65535 / 25)
                vu, tu = 2047, int((d * tau[i] + 18) * 4095 / 36)
                data = bytes([node, pu >> 8, pu & 0xFF, vu >> 4, ((vu & 0xF) << 4) | (tu >> 8), tu & 0xFF])
                lines.append(candump(t0 + t, 0x000, data))
                continue
            turns = d * (q[i] - offsets[i]) * gear / (2 * math.pi)
            current = tau[i] / (d * gear * kt)
            if spike is not None and spike == (k, i):
                current = 1e6
            lines.append(candump(t0 + t, node << 5 | 0x09, struct.pack("<ff", turns, 0.0)))
            if torques:  # firmware 0.6 Get_Torques: motor-side torque, N m
                motor_tau = tau[i] / (d * gear)
                lines.append(candump(t0 + t, node << 5 | 0x1C, struct.pack("<ff", motor_tau, motor_tau)))
                continue
            lines.append(candump(t0 + t, node << 5 | 0x14, struct.pack("<ff", current, current)))
    path.write_text("\n".join(lines) + "\n")
    return n


def ingest(tmp_path, logs, *args):
    out = tmp_path / "ds.npz"
    rc = main(["ingest", *map(str, logs), "--out", str(out), "--toe", "I", "--length", "0.04",
               "--filter-window", "1", *map(str, args)])
    return rc, out


def check_forces(ds, tol, t0=1.7e9, xy_tol=1e-6, hip_height=0.25):
    t = ds.time.numpy() - t0
    want = np.array([force_at(tk) for tk in t])
    np.testing.assert_allclose(ds.forces.numpy(), want, rtol=0, atol=tol)
    x = np.array([toe_at(tk)[0] for tk in t])
    np.testing.assert_allclose(ds.toe_position[:, 0].numpy(), x, atol=xy_tol)
    np.testing.assert_allclose(ds.toe_position[:, 1].numpy(), -DEPTH, atol=xy_tol)


def test_hand_computed_point():
    """l1 = 0.1, l2 = 0.2, toe straight down with g = pi/3: L = 0.2302776 m, L' = -0.1106218 m;
    a ground force (0, 10) N is held by tau = (5 L', -5 L') = (-0.5531088, 0.5531088) N m, i.e.
    -5.684572 A and +5.684572 A at k_t = 0.0973 N m/A."""
    leg = FiveBarLeg(0.1, 0.2)
    q = torch.tensor([math.pi / 3, -math.pi / 3], dtype=torch.float64)
    torch.testing.assert_close(leg.forward_kinematics(q), torch.tensor([0.0, -0.2302776], dtype=torch.float64),
                               atol=1e-7, rtol=0)
    tau = leg.holding_torques(q, torch.tensor([0.0, 10.0], dtype=torch.float64))
    torch.testing.assert_close(tau, torch.tensor([-0.5531088, 0.5531088], dtype=torch.float64), atol=2e-7, rtol=0)
    assert (tau / 0.0973).tolist() == pytest.approx([-5.684572, 5.684572], abs=1e-6)
    f, ok = leg.ground_force(q, torch.tensor([-0.5531088, 0.5531088], dtype=torch.float64))
    assert bool(ok) and f.tolist() == pytest.approx([0.0, 10.0], abs=1e-5)
    # the test's own closed forms agree with the literals
    assert torques_coaxial(0.0, -0.2302776, (0.0, 10.0), 0.1, 0.2) == pytest.approx((-0.5531088, 0.5531088), abs=1e-6)
    assert ik_coaxial(0.0, -0.23027756, 0.1, 0.2) == pytest.approx((math.pi / 3, -math.pi / 3), abs=1e-6)


def test_ingest_recovers_prescribed_forces_and_path(tmp_path, capsys):
    n = write_log(tmp_path / "t.log")
    rc, out = ingest(tmp_path, [tmp_path / "t.log"])
    assert rc == 0, capsys.readouterr().err
    ds = load_dataset(out)
    assert len(ds) == n == 201
    check_forces(ds, tol=2e-4)  # float32 payloads
    # a flat 4 cm x 0.8 cm plate 3 cm deep: sum of depth x area = 3 x 3.2 = 9.6 cm^3 at every sample
    np.testing.assert_allclose(ds.contacts.weight_z.sum(1).numpy(), 9.6, rtol=1e-6)
    text = capsys.readouterr().out
    assert "duration 2.00 s, 201 samples x 10 segments" in text
    assert "in contact 2.00 s (100 % of samples)" in text and "masked: none" in text


@pytest.mark.parametrize("case", ["kv-odrive-gear-dir-offsets", "kv-si-links-hip", "hip-spacing", "nodes-0.6",
                                  "0.6-torques-gear"])
def test_ingest_leg_and_motor_options(tmp_path, case, capsys):
    if case == "kv-odrive-gear-dir-offsets":
        write_log(tmp_path / "t.log", kt=8.27 / 100, directions=(-1, 1), offsets=(0.1, -0.2), gear=6.0)
        args = ["--kv", "100", "--directions", "-1", "1", "--zero-offsets", "0.1", "-0.2", "--gear-ratio", "6"]
        hh = 0.25
    elif case == "kv-si-links-hip":
        write_log(tmp_path / "t.log", kt=60 / (2 * math.pi * 85), l1=0.12, l2=0.25, hip_height=0.20)
        args = ["--kv", "85", "--kt-convention", "si", "--l1", "0.12", "--l2", "0.25", "--hip-height", "0.20"]
        hh = 0.20
    elif case == "hip-spacing":
        write_log(tmp_path / "t.log", spacing=0.06)
        args = ["--hip-spacing", "0.06"]
        hh = 0.25
    elif case == "0.6-torques-gear":  # Get_Torques instead of Get_Iq: no k_t involved
        write_log(tmp_path / "t.log", torques=True, gear=6.0, directions=(1, -1))
        args = ["--firmware", "0.6", "--gear-ratio", "6", "--directions", "1", "-1", "--kt", "5.0"]
        hh = 0.25
    else:  # other node ids, firmware 0.6 layouts (Get_Iq and encoder estimates are unchanged in 0.6)
        write_log(tmp_path / "t.log", nodes=(3, 5))
        args = ["--nodes", "3", "5", "--firmware", "0.6"]
        hh = 0.25
    rc, out = ingest(tmp_path, [tmp_path / "t.log"], *args)
    assert rc == 0, capsys.readouterr().err
    check_forces(load_dataset(out), tol=5e-4, hip_height=hh)


def test_kv_is_used_not_ignored(tmp_path):
    """Currents for k_t = 8.27/100: read with --kv 100 the forces are right; with the default k_t
    (0.0973) they are all scaled by 0.0973 / 0.0827 (the bug this guards against)."""
    write_log(tmp_path / "t.log", kt=8.27 / 100)
    rc, out = ingest(tmp_path, [tmp_path / "t.log"], "--kv", "100")
    assert rc == 0
    good = load_dataset(out).forces.numpy()
    rc, out = ingest(tmp_path, [tmp_path / "t.log"])
    assert rc == 0
    np.testing.assert_allclose(load_dataset(out).forces.numpy(), good * 0.0973 / 0.0827, rtol=1e-4)


def test_ingest_mit_mode_log(tmp_path, capsys):
    write_log(tmp_path / "m.log", protocol="mit", nodes=(1, 2))
    rc, out = ingest(tmp_path, [tmp_path / "m.log"], "--protocol", "mit", "--mit-model", "AK80-9",
                     "--nodes", "1", "2")
    assert rc == 0, capsys.readouterr().err
    # 16-bit position (3.8e-4 rad) and 12-bit torque (8.8e-3 N m) codes: ~1 mm and ~0.1 N
    check_forces(load_dataset(out), tol=0.15, xy_tol=1.5e-3)
    # the same bytes read as an AK10-9 (T +-65 N m) scale the torques: a wrong model is visible
    rc, out = ingest(tmp_path, [tmp_path / "m.log"], "--protocol", "mit", "--mit-model", "AK10-9",
                     "--nodes", "1", "2")
    assert rc != 0 or np.abs(load_dataset(out).forces.numpy()[:, 1]).max() > 20


def test_current_spike_is_masked_and_counted(tmp_path, capsys):
    write_log(tmp_path / "t.log", spike=(100, 0))
    rc, out = ingest(tmp_path, [tmp_path / "t.log"])
    assert rc == 0
    check_forces(load_dataset(out), tol=0.02)  # the neighbours bridge the dropped sample
    assert "masked: 1 node 0: |current| above 80 A (max 1e+06)" in capsys.readouterr().out


def test_duplicated_frames_are_dropped_and_counted(tmp_path, capsys):
    write_log(tmp_path / "t.log")
    lines = (tmp_path / "t.log").read_text().splitlines()
    (tmp_path / "d.log").write_text("\n".join(x for x in lines for _ in range(2)) + "\n")
    rc, out = ingest(tmp_path, [tmp_path / "d.log"])
    assert rc == 0
    check_forces(load_dataset(out), tol=2e-4)
    assert f"dropped {len(lines)} duplicate frame(s)" in capsys.readouterr().out


def test_hip_height_sign_slip_is_an_early_error(tmp_path, capsys):
    write_log(tmp_path / "t.log")
    rc, out = ingest(tmp_path, [tmp_path / "t.log"], "--hip-height", "-0.25")
    assert rc == 2 and not out.exists()
    assert "argument --hip-height" in capsys.readouterr().err


def test_wrong_link_lengths_are_early_errors(tmp_path, capsys):
    write_log(tmp_path / "t.log")
    for links, hint in ((("0.10", "0.20"), "never touches the sand"), (("0.2", "0.45"), "deeper than max_depth")):
        rc, out = ingest(tmp_path, [tmp_path / "t.log"], "--l1", links[0], "--l2", links[1])
        err = capsys.readouterr().err
        assert rc == 2 and not out.exists() and hint in err and "--l1/--l2" in err


def test_reversed_trial_is_an_error(tmp_path, capsys):
    write_log(tmp_path / "a.log")
    write_log(tmp_path / "rev.log", reverse=True)
    rc, out = ingest(tmp_path, [tmp_path / "a.log", tmp_path / "rev.log"])
    err = capsys.readouterr().err
    assert rc == 2 and not out.exists() and "other direction" in err and "rev.log" in err


def test_short_trial_is_an_error_or_cropped(tmp_path, capsys):
    write_log(tmp_path / "a.log")
    write_log(tmp_path / "short.log", t_end=1.2)
    rc, out = ingest(tmp_path, [tmp_path / "a.log", tmp_path / "short.log"])
    err = capsys.readouterr().err
    assert rc == 2 and "covers 0.120 m of the 0.200 m path (60 %" in err and "short.log" in err
    rc, out = ingest(tmp_path, [tmp_path / "a.log", tmp_path / "short.log"], "--crop-trials")
    assert rc == 0 and "irft ingest: warning: cropping every trial to 0.120 m" in capsys.readouterr().err
    ds = load_dataset(out)
    assert ds.toe_position[:, 0].max() == pytest.approx(0.02, abs=1e-3)  # -0.10 + 0.12


def test_short_air_run_is_cropped_with_crop_trials(tmp_path, capsys):
    """An air run shorter than the other air runs: the error names it and points to --crop-trials,
    and --crop-trials then crops the air runs too (it used to give the same error again). The trials
    (the same prescribed force as the air runs, so 0 N after subtraction) keep only the 0.12 m the
    short air run covers: x from -0.10 to -0.10 + 0.12 = 0.02 m, the rest masked and counted."""
    for name in ("a.log", "air1.log"):
        write_log(tmp_path / name)
    write_log(tmp_path / "air2.log", t_end=1.2)
    args = ["--air", str(tmp_path / "air1.log"), str(tmp_path / "air2.log")]
    rc, out = ingest(tmp_path, [tmp_path / "a.log"], *args)
    err = capsys.readouterr().err
    assert rc == 2 and not out.exists() and "air run 1" in err and "air2.log" in err and "--crop-trials" in err
    # the trials equal the air runs: 0 N after subtraction, no medium's forces (F70): --any-medium lets them through
    rc, out = ingest(tmp_path, [tmp_path / "a.log"], *args, "--crop-trials", "--any-medium")
    text = capsys.readouterr()
    assert rc == 0, text.err
    assert "irft ingest: warning: air runs: cropping every trial to 0.120 m" in text.err
    assert "no air-run force at this arc length" in text.out
    ds = load_dataset(out)
    x = ds.toe_position[:, 0]
    assert x.min() == pytest.approx(-0.10, abs=1e-6) and x.max() == pytest.approx(0.02, abs=1.5e-3)  # 1 mm a sample
    np.testing.assert_allclose(ds.forces.numpy(), 0.0, atol=5e-4)
