"""Terrain that changes over the ground (``rft.terrain``) and a walk's stances (``rft.walks``), against
hand-derived values and per-sample loops over the homogeneous forward model."""

import math

import pytest
import torch

from irft_torch import rft
from irft_torch.rft import FourierStressMap, IToe, TerrainField, course_path, footholds, walk

LOOSE = FourierStressMap.poppy_seeds_loose()
CLOSE = FourierStressMap.poppy_seeds_close()
GENERIC = FourierStressMap.generic()


def _angles(n=50, seed=0):
    g = torch.Generator().manual_seed(seed)
    beta = (torch.rand(n, generator=g, dtype=torch.float64) - 0.5) * math.pi
    gamma = (torch.rand(n, generator=g, dtype=torch.float64) - 0.5) * 2 * math.pi
    return beta, gamma


def test_two_media_is_each_medium_far_from_the_boundary_and_the_mean_on_it():
    field = TerrainField.two_media(LOOSE, CLOSE, boundary=1.0, width=0.01, angle=0.0)
    b, g = _angles()
    before = field(b, g, torch.tensor([0.0, 5.0], dtype=torch.float64))  # 100 widths before: logistic 4e-44
    beyond = field(b, g, torch.tensor([2.0, -3.0], dtype=torch.float64))
    on = field(b, g, torch.tensor([1.0, 0.7], dtype=torch.float64))
    torch.testing.assert_close(before, LOOSE(b, g), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(beyond, CLOSE(b, g), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(on, 0.5 * (LOOSE(b, g) + CLOSE(b, g)), rtol=1e-12, atol=1e-12)
    # turned by 90 degrees the boundary runs along x: y decides
    turned = TerrainField.two_media(LOOSE, CLOSE, boundary=0.0, width=0.01, angle=math.pi / 2)
    torch.testing.assert_close(turned(b, g, torch.tensor([9.0, -1.0], dtype=torch.float64)), LOOSE(b, g))


def test_compaction_gradient_is_linear_in_the_scale_along_its_span():
    field = TerrainField.compaction_gradient(GENERIC, scales=(0.5, 1.5), span=(0.0, 2.0))
    b, g = _angles()
    for x, k in ((-1.0, 0.5), (0.0, 0.5), (0.5, 0.75), (1.0, 1.0), (2.0, 1.5), (7.0, 1.5)):
        got = field(b, g, torch.tensor([x, 0.3], dtype=torch.float64))
        torch.testing.assert_close(got, k * GENERIC(b, g), rtol=1e-12, atol=1e-14)


def test_random_patches_share_sums_to_one_and_each_centre_is_its_medium():
    field = TerrainField.random_patches([LOOSE, CLOSE, GENERIC.scaled(0.3, 0.3)], n_patches=9,
                                        extent=(0.0, 3.0, -1.0, 1.0), edge=0.005, seed=3)
    s = torch.rand(400, 2, dtype=torch.float64) * torch.tensor([3.0, 2.0]) - torch.tensor([0.0, 1.0])
    w = field.shares(s)
    assert w.shape == (400, 3) and bool((w >= 0).all())
    torch.testing.assert_close(w.sum(-1), torch.ones(400, dtype=torch.float64))
    b, g = _angles()
    media = [LOOSE, CLOSE, GENERIC.scaled(0.3, 0.3)]
    checked = 0
    for k in range(9):  # at a centre 0.4 m or more from the rest (blend exp(-0.4^2 / (2 0.005 0.82)) < 1e-8)
        c = field.centres[k]
        others = torch.cat([field.centres[:k], field.centres[k + 1:]])
        if float((others - c).norm(dim=-1).min()) < 0.4:
            continue
        torch.testing.assert_close(field(b, g, c), media[int(field.owner[k])](b, g), rtol=1e-7, atol=1e-9)
        checked += 1
    assert checked >= 2
    # the same seed, the same field
    again = TerrainField.random_patches(media, n_patches=9, extent=(0.0, 3.0, -1.0, 1.0), edge=0.005, seed=3)
    torch.testing.assert_close(again.shares(s), w, rtol=0, atol=0)


def test_forces_over_a_field_equal_each_sample_forced_at_its_own_place():
    toe = IToe(0.03, 0.01, n_segments=6)
    path = course_path(-0.4, 0.06, start=(0.0, 0.0), n_steps=12)
    c = rft.contacts(toe, path)
    field = TerrainField.two_media(LOOSE, CLOSE, boundary=0.05, width=0.02)
    s = torch.stack([torch.linspace(-0.1, 0.2, len(path), dtype=torch.float64),
                     torch.zeros(len(path), dtype=torch.float64)], -1)
    got = rft.forces(field, c, locations=s)
    want = torch.stack([rft.forces(field.at(s[t]), c[t:t + 1])[0] for t in range(len(path))])
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)
    # every sample at one place: the homogeneous forward model with the blended map there
    here = torch.tensor([0.05, 0.0], dtype=torch.float64)
    blend = lambda b, g: 0.5 * (LOOSE(b, g) + CLOSE(b, g))  # noqa: E731
    torch.testing.assert_close(rft.forces(field, c, locations=here.expand(len(path), 2)), rft.forces(blend, c))
    seg = rft.segment_forces(field, c, locations=s)
    torch.testing.assert_close(seg.sum(-2), got)


def test_bad_locations_are_refused_by_name():
    toe = IToe(0.03, 0.01, n_segments=4)
    c = rft.contacts(toe, course_path(-0.4, 0.05, start=(0.0, 0.0), n_steps=5))
    field = TerrainField.uniform(GENERIC)
    with pytest.raises(ValueError, match="locations"):
        rft.forces(field, c)  # a field needs places
    with pytest.raises(ValueError, match="locations"):
        rft.forces(field, c, locations=torch.zeros(4, 2))
    with pytest.raises(ValueError, match="locations"):
        rft.forces(field, c, locations=torch.full((5, 2), math.nan))
    with pytest.raises(ValueError, match="locations"):
        rft.forces(field, c, locations=torch.zeros(5, 3))
    with pytest.raises(ValueError, match="width"):
        TerrainField.two_media(LOOSE, CLOSE, width=0.0)
    with pytest.raises(ValueError, match="span"):
        TerrainField.compaction_gradient(GENERIC, span=(1.0, 1.0))


def test_footholds_are_a_stride_apart_along_the_route_with_its_heading():
    p, psi = footholds([(0.0, 0.0), (1.0, 0.0), (1.0, 1.0)], stride=0.25)
    assert p.shape == (9, 2)  # 0, 0.25, ..., 2.0 m along a 2 m route
    torch.testing.assert_close(p[3], torch.tensor([0.75, 0.0], dtype=torch.float64))
    torch.testing.assert_close(p[6], torch.tensor([1.0, 0.5], dtype=torch.float64))
    torch.testing.assert_close(psi[:4], torch.zeros(4, dtype=torch.float64))
    torch.testing.assert_close(psi[5:], torch.full((4,), math.pi / 2, dtype=torch.float64))
    with pytest.raises(ValueError, match="stride"):
        footholds([(0.0, 0.0), (1.0, 0.0)], stride=-1.0)
    with pytest.raises(ValueError, match="route"):
        footholds([(0.0, 0.0)], stride=0.1)


def test_a_walk_places_every_sample_at_its_foothold_plus_the_drag():
    toe = IToe(0.03, 0.01, n_segments=5)
    stroke = course_path(-0.3, 0.08, start=(0.0, 0.0), n_steps=10)  # drags 0.08 cos(0.3) m forward
    p = torch.tensor([[1.0, 2.0], [3.0, -1.0]], dtype=torch.float64)
    psi = torch.tensor([0.0, math.pi / 2], dtype=torch.float64)
    w = walk(toe, stroke, p, psi)
    T = len(stroke)
    assert len(w) == 2 * T and w.n_stances == 2 and w.contacts.shape == (2 * T, 5)
    torch.testing.assert_close(w.locations[0], p[0])
    torch.testing.assert_close(w.locations[T], p[1])
    drag = 0.08 * math.cos(0.3)
    torch.testing.assert_close(w.locations[T - 1], p[0] + torch.tensor([drag, 0.0], dtype=torch.float64))
    torch.testing.assert_close(w.locations[-1], p[1] + torch.tensor([0.0, drag], dtype=torch.float64))
    assert w.stance.tolist() == [0] * T + [1] * T
    c = rft.contacts(toe, stroke)
    torch.testing.assert_close(w.contacts.beta[T:], c.beta)
    # a uniform field over a walk: the homogeneous forces, stance after stance
    F = rft.forces(TerrainField.uniform(GENERIC), w.contacts, locations=w.locations)
    torch.testing.assert_close(F, torch.cat([rft.forces(GENERIC, c)] * 2))
    with pytest.raises(ValueError, match="headings"):
        walk(toe, stroke, p, psi[:1])
