"""3-D RFT (rft.mesh, rft.contacts3d, rft.forces3d) against independent computations: the planar model,
the rover-wheel authors' stored predictions, hand-derived plates, finite differences and an independent
numpy transcription of the authors' formulas (shared/reference/rft3d_facts.md)."""

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from irft_torch.rft import (
    Contacts3D,
    CToe,
    FourierStressMap,
    IToe,
    Mesh,
    PolylineToe,
    contacts,
    contacts_3d,
    element_kinematics,
    forces,
    forces_3d,
    planar_motion,
    pose_path,
    read_mesh,
    rectangle_path,
    rotating_leg_path,
    spline_path,
    wheel_mesh,
)
from irft_torch.rft.paths import Path as RFTPath
from irft_torch.rft.stress_maps import wrap_beta

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "rover_wheel"
GEN = FourierStressMap.generic()

# ---- an independent numpy transcription of RFT3Dfunc.m (facts file sections 4-7) -----------------------------
LI = dict(A00=0.206, A10=0.169, B11=0.212, B01=0.358, Bm11=0.055, C11=-0.124, C01=0.253, Cm11=0.007, D10=0.088)


def li_maps(b, g, zeta=1.0):
    ax = zeta * (LI["C11"] * np.cos(2 * b + g) + LI["C01"] * np.cos(g) + LI["Cm11"] * np.cos(-2 * b + g)
                 + LI["D10"] * np.sin(2 * b))
    az = zeta * (LI["A00"] + LI["A10"] * np.cos(2 * b) + LI["B11"] * np.sin(2 * b + g) + LI["B01"] * np.sin(g)
                 + LI["Bm11"] * np.sin(-2 * b + g))
    return ax, az


def np_f1(vt):
    return 0.440850096954369 * (np.tanh(3.62263982880971 * vt - 1.60910808139526) + np.tanh(1.60910808139526)) \
        / 0.832324700111401


def np_f23(vn):
    return 1.99392673405210 * (np.arctanh(1.61146827229181 * vn - 0.973746396532650)
                               + np.arctanh(0.973746396532650)) / 5.81083560370960


def authors_force(P, N, A, V, zs, thin, zeta=1.0, ay=None):
    """World points P, normals N, velocities V (E, 3) in m, m/s; areas A (E,) m^2; thin (E,) bool -> (3,) N,
    formula by formula as the authors' code (mm, 1e-3), beta and gamma used raw (no canonical square)."""
    P, V = P * 1e3, V * 1e3
    A = A * 1e6
    zs = zs * 1e3
    speed = np.linalg.norm(V, axis=1)
    vn = V / speed[:, None]
    N = np.where((thin & ((N * vn).sum(1) < 0))[:, None], -N, N)
    include = (thin | ((N * vn).sum(1) > 0)) & (P[:, 2] < zs)
    n, v, d, a = N[include], vn[include], zs - P[include, 2], A[include]
    near = np.abs(n[:, 2]) >= 1 - 1e-3
    hv = (v + [1e-5, 0, 0]) * [1, 1, 0]
    hn = n * [1, 1, 0]
    e2 = np.where(near[:, None], hv / np.linalg.norm(hv, axis=1)[:, None], hn / np.maximum(
        np.linalg.norm(hn, axis=1), 1e-300)[:, None])
    e1 = np.cross(e2, [0, 0, 1])
    v1 = (v * e1).sum(1)[:, None] * e1
    v23 = v - v1
    beta = np.arctan2(n[:, 2], (n * e2).sum(1)) + np.pi / 2
    gamma = -np.arctan2(v23[:, 2], (v23 * e2).sum(1))
    ax, az = li_maps(beta, gamma, zeta)
    ay = li_maps(0.0, 0.0, zeta)[0] if ay is None else ay
    F1 = -np_f1(np.linalg.norm(v1, axis=1))[:, None] * ay * e1 * np.sign((v * e1).sum(1))[:, None]
    F2 = -np_f23(np.linalg.norm(v23, axis=1))[:, None] * ax[:, None] * e2
    F3 = np_f23(np.linalg.norm(v23, axis=1))[:, None] * az[:, None] * np.array([0, 0, 1.0])
    return ((d * a)[:, None] * (F1 + F2 + F3) * 1e-3).sum(0)


def random_rotation(gen, T):
    q = torch.randn(T, 4, generator=gen)
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        torch.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        torch.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], -2)


# ---- the planar model is the special case ----------------------------------------------------------------------
def _plate_path(v, n=4, depth=0.03, heading=0.0):
    t = torch.linspace(0, 1, n)
    pos = torch.stack([t * v[0], -depth + t * v[1]], -1)
    return RFTPath(t, pos, torch.full((n,), heading), torch.tensor(v).expand(n, 2), torch.zeros(n))


def planar_cases():
    """Built inside a test (float64 default)."""
    return {
        "C-toe spline": (CToe(0.02, 0.008, n_segments=12),
                         spline_path([(-0.2, 0.0), (-0.1, -0.05), (0.1, 0.0), (0.2, -0.05)], n_steps=60)),
        "I-toe tilted rectangle": (IToe(0.03, 0.01, tilt=0.4, n_segments=7),
                                   rectangle_path(penetration=0.05, shear=0.1, n_steps=60)),
        "rotating C-leg": (CToe(0.03, 0.01, n_segments=9, opening="left"),
                           rotating_leg_path(hip=(0.0, 0.02), n_steps=60)),
        "polyline": (PolylineToe([(-0.02, 0.01), (0.0, 0.0), (0.02, 0.015)], 0.012),
                     pose_path(torch.linspace(0, 2, 40), 0.1 - 0.1 * torch.linspace(0, 2, 40),
                               -0.03 * torch.sin(torch.linspace(0, 3, 40)), 0.8 * torch.linspace(0, 2, 40))),
        # exactly tangential (a horizontal plate dragged sideways: n . v = 0), exactly vertical, toward -x
        "plate dragged +x": (IToe(0.02, 0.008, n_segments=5), _plate_path((0.02, 0.0))),
        "plate dragged -x": (IToe(0.02, 0.008, n_segments=5), _plate_path((-0.02, 0.0))),
        "plate pushed down": (IToe(0.02, 0.008, n_segments=5), _plate_path((0.0, -0.01))),
        "vertical plate down": (IToe(0.02, 0.008, tilt=math.pi / 2, n_segments=5), _plate_path((0.0, -0.01))),
    }


PLANAR_NAMES = ["C-toe spline", "I-toe tilted rectangle", "rotating C-leg", "polyline", "plate dragged +x",
                "plate dragged -x", "plate pushed down", "vertical plate down"]


@pytest.mark.parametrize("name", PLANAR_NAMES)
def test_planar_toe_as_two_faced_mesh_equals_planar_model(name):
    toe, path = planar_cases()[name]
    c2 = contacts(toe, path)
    c3 = contacts_3d(Mesh.from_toe(toe), surface=0.0, **planar_motion(path))
    smap = FourierStressMap.poppy_seeds_close()
    f2, f3 = forces(smap, c2), forces_3d(smap, c3, alpha_y=0.3)
    torch.testing.assert_close(f3[:, [0, 2]], f2, atol=1e-12, rtol=1e-12)
    assert f3[:, 1].abs().max() == 0 and c3.weight_y.abs().max() == 0 and c3.weight_x[..., 1].abs().max() == 0
    # the weights, segment by segment: every planar segment with weight is one 3-D entry, nothing else is
    T, M = c2.shape
    for t in range(T):
        live = c3.element[t] >= 0
        seg = c3.element[t, live]
        assert sorted(seg.tolist()) == torch.nonzero(c2.weight_z[t] > 0).reshape(-1).tolist()
        for name3, name2 in (("weight_x", "weight_x"), ("weight_z", "weight_z")):
            w3 = getattr(c3, name3)[t, live]
            w3 = w3[:, 0] if w3.ndim == 2 else w3
            torch.testing.assert_close(w3, getattr(c2, name2)[t, seg], atol=1e-12, rtol=1e-12)
        torch.testing.assert_close(c3.gamma[t, live], c2.gamma[t, seg], atol=1e-12, rtol=0)
        gap = wrap_beta(c3.beta[t, live] - c2.beta[t, seg] + 1e-6) - 1e-6  # equal modulo pi
        assert (gap.abs() < 1e-12).all()


def test_three_d_forces_match_an_independent_transcription_under_random_rotations():
    """Random body, random rigid motions (rotation, spin, drift in y): forces_3d equals the authors' formulas
    evaluated raw in numpy (their beta in [0, pi], |gamma| > pi/2 as it comes, no canonical square)."""
    gen = torch.Generator().manual_seed(3)
    E, T = 300, 12
    P = (torch.rand(E, 3, generator=gen) - 0.5) * 0.08
    N = torch.randn(E, 3, generator=gen)
    N[:20] = torch.tensor([0.0, 0.0, -1.0]) + 1e-4 * torch.randn(20, 3, generator=gen)  # near-horizontal
    N = N / N.norm(dim=-1, keepdim=True)
    A = torch.rand(E, generator=gen) * 1e-5
    thin = torch.rand(E, generator=gen) < 0.3
    mesh = Mesh(P, N, A, thin)
    R = random_rotation(gen, T)
    v = torch.randn(T, 3, generator=gen) * 0.05
    w = torch.randn(T, 3, generator=gen) * 2.0
    x0 = torch.randn(T, 3, generator=gen) * 0.01
    zs = torch.rand(T, generator=gen) * 0.02
    smap = FourierStressMap.generic(0.7, 0.7)
    c = contacts_3d(mesh, v, w, zs, position=x0, rotation=R)
    f = forces_3d(smap, c, alpha_y=0.11)
    pts, nrm, vel = element_kinematics(mesh, v, w, position=x0, rotation=R)
    for t in range(T):
        ref = authors_force(pts[t].numpy(), nrm[t].numpy(), A.numpy(), vel[t].numpy(), float(zs[t]), thin.numpy(),
                            zeta=0.7, ay=0.11)
        np.testing.assert_allclose(f[t].numpy(), ref, rtol=1e-10, atol=1e-12)
    assert (c.beta >= -math.pi / 2).all() and (c.beta < math.pi / 2).all() and (c.gamma.abs() <= math.pi / 2).all()


def test_element_velocities_are_finite_differences_of_positions():
    """A body spinning about a tilted axis while it translates: v + w x (R p) is d/dt of x(t) + R(t) p."""
    mesh = Mesh.from_toe(CToe(0.02, 0.01, n_segments=6), n_across=3)
    axis = torch.tensor([0.3, -0.5, 0.8])
    axis = axis / axis.norm()
    w_mag, v0 = 1.7, torch.tensor([0.02, -0.01, 0.005])

    def pose(t):
        K = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        R = torch.linalg.matrix_exp(w_mag * t * K)
        return R, torch.tensor([0.0, 0.1, -0.02]) + v0 * t

    t, h = 0.37, 1e-6
    (Rm, xm), (R0, x0), (Rp, xp) = pose(t - h), pose(t), pose(t + h)
    pm, _, _ = element_kinematics(mesh, v0, w_mag * axis, position=xm, rotation=Rm)
    pp, _, _ = element_kinematics(mesh, v0, w_mag * axis, position=xp, rotation=Rp)
    _, _, vel = element_kinematics(mesh, v0, w_mag * axis, position=x0, rotation=R0)
    torch.testing.assert_close(vel, (pp - pm) / (2 * h), atol=1e-8, rtol=1e-7)


# ---- hand-derived plates ----------------------------------------------------------------------------------------
def _vertical_plate(thin: bool):
    """A 2 cm x 1 cm vertical plate in the y-z plane (normal +x), centre 3 cm deep."""
    return Mesh(torch.tensor([[0.0, 0.0, -0.03]]), torch.tensor([[1.0, 0.0, 0.0]]), torch.tensor([2e-4]),
                torch.tensor([thin]))


@pytest.mark.parametrize("thin", [True, False])
def test_plate_sliding_in_its_own_plane_feels_only_alpha_y(thin):
    """v = +y along a plate with normal +x: e2 = x, e1 = e2 x z = -y, v1 = y (|v1| = 1, f1 = 1), v23 = 0 (f23 = 0):
    F = -w alpha_y sgn(v.e1) e1 = (0, -alpha_y w, 0), w = 3 cm x 2 cm^2 (a face needs n.v > 0: a thin plate only)."""
    mesh = _vertical_plate(thin)
    c = contacts_3d(mesh, torch.tensor([[0.0, 0.05, 0.0]]), torch.zeros(1, 3), surface=0.0)
    f = forces_3d(GEN, c, alpha_y=0.2)
    if not thin:  # a closed body's face sliding in its own plane does not lead
        assert c.n_elements == 1 and c.weight_z.abs().max() == 0 and f.abs().max() == 0
        return
    torch.testing.assert_close(f, torch.tensor([[0.0, -0.2 * 6.0, 0.0]]), atol=1e-13, rtol=0)
    torch.testing.assert_close(c.weight_y[0, 0], torch.tensor([0.0, -6.0]), atol=1e-13, rtol=0)
    assert c.weight_x.abs().max() < 1e-15 and c.weight_z.abs().max() < 1e-15


@pytest.mark.parametrize("phi_deg", [20.0, 60.0, 135.0])
def test_plate_moving_obliquely_by_hand(phi_deg):
    """v = (cos phi, sin phi, 0) on a thin vertical plate with normal +x: e2 = +-x (the face that leads),
    beta = pi/2, gamma = 0, |v1| = |sin phi|, |v23| = |cos phi|; by hand with the generic map:
    alpha_x(pi/2, 0) = -C11 + C01 - C-11 = 0.370, alpha_z(pi/2, 0) = A00 - A10 = 0.037."""
    phi = math.radians(phi_deg)
    c = contacts_3d(_vertical_plate(True), torch.tensor([[math.cos(phi), math.sin(phi), 0.0]]) * 0.03,
                    torch.zeros(1, 3), surface=0.0)
    f = forces_3d(GEN, c, alpha_y=0.2)[0]
    w = 6.0
    sx, sy = math.copysign(1, math.cos(phi)), math.copysign(1, math.sin(phi))
    g1, g23 = np_f1(abs(math.sin(phi))), np_f23(abs(math.cos(phi)))
    want = torch.tensor([-g23 * 0.370 * sx * w, -g1 * 0.2 * sy * w, g23 * 0.037 * w])
    torch.testing.assert_close(f, want, atol=1e-12, rtol=1e-12)


def test_scaling_functions_hit_their_anchors():
    from irft_torch.rft.contacts3d import f1, f23

    x = torch.tensor([0.0, 1.0])
    torch.testing.assert_close(f1(x), x, atol=1e-14, rtol=0)
    torch.testing.assert_close(f23(x), x, atol=1e-14, rtol=0)
    psi = torch.deg2rad(torch.tensor([15.0, 30.0, 45.0, 60.0, 75.0]))  # the facts file's table, 2 digits
    torch.testing.assert_close(f1(torch.sin(psi)), torch.tensor([0.18, 0.59, 0.88, 0.97, 0.99]), atol=6e-3, rtol=0)
    torch.testing.assert_close(f23(torch.cos(psi)), torch.tensor([0.97, 0.90, 0.80, 0.68, 0.53]), atol=6e-3, rtol=0)


# ---- meshes ------------------------------------------------------------------------------------------------------
def test_triangle_elements_incenter_normal_area_by_hand():
    # right triangle (0,0,0), (3,0,0), (0,4,0): sides a = 5 (opposite A), b = 4, c = 3; incenter (1, 1, 0)
    m = Mesh.from_triangles(torch.tensor([[[0.0, 0, 0], [3, 0, 0], [0, 4, 0]], [[0, 0, 0], [1, 0, 0], [2, 0, 0]]]))
    assert m.n_elements == 1  # the degenerate one dropped
    torch.testing.assert_close(m.points[0], torch.tensor([1.0, 1.0, 0.0]))
    torch.testing.assert_close(m.normals[0], torch.tensor([0.0, 0.0, 1.0]))
    assert float(m.areas[0]) == 6.0


def _cube_triangles(s=0.02):
    """A closed cube of side s, outward (counter-clockwise) triangles, (12, 3, 3)."""
    v = torch.tensor([[x, y, z] for x in (0, s) for y in (0, s) for z in (0, s)], dtype=torch.float64)
    faces = [(0, 1, 3), (0, 3, 2), (4, 6, 7), (4, 7, 5), (0, 4, 5), (0, 5, 1), (2, 3, 7), (2, 7, 6), (0, 2, 6),
             (0, 6, 4), (1, 5, 7), (1, 7, 3)]
    return v[torch.tensor(faces)]


def test_read_mesh_stl_and_mat_round_trip(tmp_path):
    pytest.importorskip("stl")
    from scipy.io import savemat
    from stl import mesh as stl_mesh

    tri = _cube_triangles(20.0)  # mm
    m = stl_mesh.Mesh(np.zeros(12, dtype=stl_mesh.Mesh.dtype))
    m.vectors[:] = tri.numpy()
    m.save(str(tmp_path / "cube.stl"))
    with pytest.raises(ValueError, match="unit"):
        read_mesh(tmp_path / "cube.stl")
    body = read_mesh(tmp_path / "cube.stl", unit="mm")
    assert body.n_elements == 12
    assert float(body.areas.sum()) == pytest.approx(6 * 0.02**2, rel=1e-6)  # float32 STL
    centre = torch.tensor([0.01, 0.01, 0.01])
    assert ((body.points - centre) * body.normals).sum(-1).min() > 0  # outward
    savemat(tmp_path / "cube.mat", {"Points": body.points.numpy().T * 1e3, "Normals": body.normals.numpy().T,
                                    "Area": body.areas.numpy() * 1e6})
    back = read_mesh(tmp_path / "cube.mat")  # millimetres by default, (3, E) layout
    torch.testing.assert_close(back.points, body.points)
    torch.testing.assert_close(back.areas, body.areas)


def test_wheel_mesh_areas_and_front_half_contact():
    R, W = 0.0625, 0.06
    m = wheel_mesh(R, W, n_around=240, n_across=4, grousers=12, grouser_height=0.005)
    rim = (~m.thin) & (m.normals[:, 1] == 0)
    assert float(m.areas[rim].sum()) == pytest.approx(2 * math.pi * R * W, rel=1e-12)
    side = m.normals[:, 1] != 0
    assert float(m.areas[side].sum()) == pytest.approx(2 * math.pi * R**2, rel=1e-12)
    assert float(m.areas[m.thin].sum()) == pytest.approx(12 * 0.005 * W, rel=1e-12)
    # rolling toward +x at 2 cm sinkage: of the rim only the front half below the surface leads
    smooth = wheel_mesh(R, W, n_around=240, n_across=4)
    c = contacts_3d(smooth, torch.tensor([[0.01, 0.0, 0.0]]), torch.tensor([[0.0, 0.2, 0.0]]), surface=0.02 - R)
    pts = smooth.points[c.element[0][c.element[0] >= 0]]
    assert (pts[:, 0] > 0).all() and (pts[:, 2] < 0.02 - R).all()
    assert (smooth.normals[c.element[0][c.element[0] >= 0], 1] == 0).all()  # sidewalls in their plane: not leading


def test_chunking_does_not_change_contacts(monkeypatch):
    import irft_torch.rft.contacts3d as c3d

    mesh = wheel_mesh(0.05, 0.04, n_around=60, n_across=3, grousers=6, grouser_height=0.004)
    T = 7
    v = torch.stack([torch.full((T,), 0.01), torch.linspace(-0.005, 0.005, T), torch.zeros(T)], -1)
    w = torch.stack([torch.zeros(T), torch.linspace(0.0, 0.4, T), torch.zeros(T)], -1)
    zs = torch.linspace(-0.045, -0.02, T)
    whole = c3d.contacts_3d(mesh, v, w, zs)
    monkeypatch.setattr(c3d, "_CHUNK_ELEMENTS", 2 * mesh.n_elements)  # 2 samples per chunk
    parts = c3d.contacts_3d(mesh, v, w, zs)
    for k, val in whole.as_dict().items():
        assert torch.equal(val, getattr(parts, k)), k


def test_forces_3d_is_differentiable_in_the_motion():
    mesh = Mesh.from_toe(CToe(0.02, 0.01, n_segments=5), n_across=2)
    v = torch.tensor([[0.02, 0.01, -0.015]], requires_grad=True)
    w = torch.tensor([[0.1, -0.4, 0.2]])

    def f(v):
        return forces_3d(GEN, contacts_3d(mesh, v, w, surface=0.01, position=torch.tensor([[0.0, 0.0, -0.01]])))

    assert torch.autograd.gradcheck(f, (v,), eps=1e-7, atol=1e-6)


# ---- the rover wheels: the authors' stored predictions ------------------------------------------------------------
@pytest.mark.skipif(not DATA.is_dir(), reason="rover-wheel data not present (../shared/data/rover_wheel)")
@pytest.mark.parametrize("wheel", ["smooth", "grouser"])
def test_authors_wheel_predictions_reproduced(wheel):
    """All runs of a wheel from its mesh at the authors' inputs: relative RMS difference per slip angle and axis
    (over runs, divided by the RMS force magnitude) below 1e-5 (the authors computed in single precision)."""
    from irft_torch.data import wheel as wd

    runs = wd.read_wheel_runs(DATA, wheel, None)
    c = contacts_3d(wd.read_wheel_mesh(DATA, wheel), **wd.wheel_motion(runs, as_commanded=True))
    f = forces_3d(FourierStressMap.generic(0.6, 0.6), c)  # alpha_y = alpha_x(0, 0) = 0.0816
    ref = torch.tensor([[r.rft_force[0], r.rft_lateral, r.rft_force[1]] for r in runs])
    psi = torch.tensor([r.slip_angle_deg for r in runs])
    assert len(psi.unique()) == 7
    for a in psi.unique():
        m = psi == a
        rel = (f[m] - ref[m]).pow(2).mean(0).sqrt() / ref[m].pow(2).sum(-1).mean().sqrt()
        assert rel.max() < 1e-5, (float(a), rel.tolist())


# ---- bad input ----------------------------------------------------------------------------------------------------
def test_bad_input_errors():
    toe_mesh = Mesh.from_toe(IToe(0.02, 0.01))
    v, w = torch.zeros(2, 3), torch.zeros(2, 3)
    with pytest.raises(ValueError, match="unit"):
        Mesh(torch.zeros(1, 3), torch.tensor([[0.0, 0, 2]]), torch.ones(1))
    with pytest.raises(ValueError, match=r"points \(E, 3\)"):
        Mesh(torch.zeros(2, 2), torch.zeros(2, 3), torch.ones(2))
    with pytest.raises(ValueError, match="NaN"):
        Mesh(torch.full((1, 3), float("nan")), torch.tensor([[0.0, 0, 1]]), torch.ones(1))
    with pytest.raises(ValueError, match="areas"):
        Mesh(torch.zeros(1, 3), torch.tensor([[0.0, 0, 1]]), -torch.ones(1))
    with pytest.warns(UserWarning, match="millimetres"):
        Mesh(torch.tensor([[0.0, 0, 0], [62.5, 0, 0]]), torch.tensor([[0.0, 0, 1]] * 2), torch.ones(2))
    with pytest.raises(TypeError, match="Mesh"):
        contacts_3d(IToe(0.02, 0.01), v, w, 0.0)
    with pytest.raises(ValueError, match="velocity"):
        contacts_3d(toe_mesh, torch.zeros(2, 2), w, 0.0)
    with pytest.raises(ValueError, match="NaN"):
        contacts_3d(toe_mesh, torch.full((2, 3), float("nan")), w, 0.0)
    with pytest.raises(ValueError, match="rotation"):
        contacts_3d(toe_mesh, v, w, 0.0, rotation=2 * torch.eye(3).expand(2, 3, 3))
    with pytest.raises(ValueError, match="surface"):
        contacts_3d(toe_mesh, v, w, torch.zeros(3))
    with pytest.raises(ValueError, match="angular_velocity"):
        contacts_3d(toe_mesh, v, torch.zeros(3, 3), 0.0)
    c = contacts_3d(toe_mesh, torch.tensor([[0.01, 0.0, -0.01]] * 2), w, 0.05)
    with pytest.raises(ValueError, match="alpha_y must be None"):
        forces_3d(lambda b, g: torch.zeros(*b.shape, 3), c, alpha_y=0.1)
    with pytest.raises(ValueError, match="returned shape"):
        forces_3d(lambda b, g: torch.zeros(*b.shape, 4), c)
    with pytest.raises(ValueError, match="alpha_y"):
        forces_3d(GEN, c, alpha_y=[0.1, 0.2])
    with pytest.raises(TypeError, match="Contacts3D"):
        forces_3d(GEN, contacts(IToe(0.02, 0.01), _plate_path((0.01, 0.0))))
    with pytest.raises(ValueError, match="weight_x"):
        Contacts3D(c.beta, c.gamma, c.weight_z, c.weight_y, c.weight_z)
