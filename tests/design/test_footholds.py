"""Foothold scores and the greedy planner (``design.footholds``) against the model's own conditioning done the
long way (the posterior variance before and after a stance is added), and the planner's field against a
per-place loop of ``predict_forces``."""

import pytest
import torch

from irft_torch import InverseRFT, rft
from irft_torch.design import Region, Stance, foothold_scores, force_field, plan_footholds, plan_stances
from irft_torch.rft import CToe, FourierStressMap, TerrainField, course_path
from irft_torch.rft.contacts import Contacts

F64 = torch.float64


@pytest.fixture(scope="module")
def setup():
    stance = Stance.of_stroke(CToe(0.025, 0.02, n_segments=5),
                              course_path([-0.8, -0.3, 0.4], 0.06, start=(0.0, 0.0), n_steps=8))
    field = TerrainField.two_media(FourierStressMap.poppy_seeds_loose(), FourierStressMap.poppy_seeds_close(),
                                   boundary=0.5, width=0.05)
    feet = torch.stack([torch.linspace(0.0, 0.6, 4, dtype=F64), torch.zeros(4, dtype=F64)], -1)
    c = Contacts.cat([stance.at(p) for p in feet])
    F = rft.forces(field, c, locations=c.locations)
    F = F + 0.02 * F.abs().mean(0) * torch.randn(F.shape, generator=torch.Generator().manual_seed(0), dtype=F64)
    model = InverseRFT(c, F, hyper_posterior="map")
    model.fit(n_iter=60, progress=False)
    return stance, model


def test_scores_are_the_fall_of_the_posterior_variance_over_the_region(setup):
    stance, model = setup
    region = Region.square(4)
    places = torch.tensor([[0.2, 0.3], [1.2, 0.0]], dtype=F64)
    cands = torch.tensor([[0.3, 0.0], [1.1, 0.1], [2.5, 0.0]], dtype=F64)
    got = foothold_scores(model, stance, cands, places, region)
    b, g = region.beta, region.gamma
    prior = model.hypers.prior_variance.detach()
    before = model.stress_map(b, g, locations=places).variance  # (L, N, 2)
    for k, p in enumerate(cands):
        after = model.backend.condition(stance.at(p))
        q = Contacts.points(b.repeat(2), g.repeat(2)).with_locations(places.repeat_interleave(len(b), 0))
        var_after = after.posterior(q).variance.T.reshape(2, len(b), 2)
        want = ((before - var_after) * region.weight[None, :, None]).sum(1).mean(0) / prior
        torch.testing.assert_close(got[k], want.mean(), rtol=1e-6, atol=1e-10)
    assert got[1] > got[0] and got[1] > got[2]  # beside the unexplored place beats the walked one and far away
    assert 0 <= float(got.min()) and float(got.max()) < 1


def test_force_field_is_each_place_predicted_on_its_own(setup):
    stance, model = setup
    places = torch.tensor([[0.1, 0.0], [0.9, -0.2], [0.45, 0.3]], dtype=F64)
    field = force_field(model, stance, places)
    assert field.mean.shape == (3, len(stance.contacts), 2)
    for k, p in enumerate(places):
        one = model.predict_forces(stance.at(p))
        torch.testing.assert_close(field.mean[k], one.mean, rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(field.variance[k], one.variance, rtol=1e-10, atol=1e-12)


def test_planner_steps_within_reach_and_refuses_none_in_reach(setup):
    stance, model = setup
    gx, gy = torch.meshgrid(torch.arange(0.0, 2.01, 0.2, dtype=F64), torch.arange(-0.4, 0.41, 0.2, dtype=F64),
                            indexing="ij")
    cands = torch.stack([gx.reshape(-1), gy.reshape(-1)], -1)
    roi = torch.tensor([[1.5, 0.0], [1.8, 0.3]], dtype=F64)
    plan = plan_footholds(model, stance, torch.tensor([0.6, 0.0], dtype=F64), 3, 0.45, cands, roi, Region.square(4))
    assert plan.shape == (3, 2)
    steps = torch.cat([torch.tensor([[0.6, 0.0]], dtype=F64), plan]).diff(dim=0).norm(dim=-1)
    assert bool((steps <= 0.45 + 1e-12).all())
    assert float(plan[-1, 0]) > 0.6  # heads for the region of interest
    with pytest.raises(ValueError, match="reach"):
        plan_footholds(model, stance, torch.tensor([9.0, 9.0], dtype=F64), 1, 0.3, cands, roi)
    planar = InverseRFT(stance.contacts, rft.forces(FourierStressMap.generic(), stance.contacts) + 0.01,
                        hyper_posterior="map")
    with pytest.raises(ValueError, match="model"):
        foothold_scores(planar, stance, cands, roi)


def test_a_gait_library_plan_takes_the_best_pair_of_foothold_and_stroke(setup):
    """The first step of ``plan_stances`` is the argmax over every (stroke, candidate in reach) of the scores that
    ``foothold_scores`` (checked above against conditioning the long way) gives each stroke; one stroke gives
    ``plan_footholds``' plan; a single stance (not a sequence) is refused by name."""
    stance, model = setup
    tilted = Stance.of_stroke(CToe(0.025, 0.02, n_segments=5),
                              course_path([-1.2, -0.6, 0.0], 0.06, start=(0.0, 0.0), heading=0.6, n_steps=8))
    cands = torch.tensor([[0.7, 0.0], [0.9, 0.2], [1.0, -0.2], [2.5, 0.0]], dtype=F64)
    roi = torch.tensor([[1.0, 0.0], [0.4, 0.3]], dtype=F64)
    region = Region.square(4)
    start = torch.tensor([0.6, 0.0], dtype=F64)
    feet, which = plan_stances(model, [stance, tilted], start, 2, 0.5, cands, roi, region)
    near = cands[:3]  # within 0.5 m of the start
    scores = torch.stack([foothold_scores(model, s, near, roi, region) for s in (stance, tilted)])
    best = int(scores.argmax())
    assert int(which[0]) == best // 3
    torch.testing.assert_close(feet[0], near[best % 3])
    assert which.shape == (2,) and feet.shape == (2, 2)
    one = plan_stances(model, [stance], start, 2, 0.5, cands, roi, region)
    torch.testing.assert_close(one[0], plan_footholds(model, stance, start, 2, 0.5, cands, roi, region))
    assert one[1].tolist() == [0, 0]
    with pytest.raises(TypeError, match="stances"):
        plan_stances(model, [], start, 1, 0.5, cands, roi)
    with pytest.raises(TypeError, match="stances"):
        plan_stances(model, stance, start, 1, 0.5, cands, roi)


@pytest.fixture(scope="module")
def drawn(setup):
    """The fixture's data fitted with the default hyperparameter posterior (draws)."""
    _, plug = setup
    model = InverseRFT(plug.backend.train_contacts, plug.backend.train_forces)  # hyper_posterior="laplace"
    model.fit(n_iter=60, progress=False)
    return model


def test_a_model_with_draws_scores_the_weighted_average_of_its_draws_scores(setup, drawn):
    """With a hyperparameter posterior (the default) and ``draws=True``, a foothold's score is the draws' scores,
    each the long way (the draw's posterior variance before and after the stance), averaged with the posterior's
    weights; by default it is scored at the mode alone."""
    stance, model = setup[0], drawn
    backends, weights = model._weighted_backends()
    assert weights is not None and len(backends) > 1
    region = Region.square(3)
    places = torch.tensor([[0.2, 0.3], [1.2, 0.0]], dtype=F64)
    cands = torch.tensor([[0.3, 0.0], [1.1, 0.1]], dtype=F64)
    b, g = region.beta, region.gamma
    q = Contacts.points(b.repeat(2), g.repeat(2)).with_locations(places.repeat_interleave(len(b), 0))
    want = torch.zeros(len(cands), dtype=F64)
    for backend, w in zip(backends, weights):
        before = backend.posterior(q).variance.T.reshape(2, len(b), 2)
        prior = backend.hypers.prior_variance.detach()
        for k, p in enumerate(cands):
            after = backend.condition(stance.at(p)).posterior(q).variance.T.reshape(2, len(b), 2)
            want[k] += w * (((before - after) * region.weight[None, :, None]).sum(1).mean(0) / prior).mean()
    got = foothold_scores(model, stance, cands, places, region, draws=True)
    torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-10)
    mode = foothold_scores(model, stance, cands, places, region)
    before = model.backend.posterior(q).variance.T.reshape(2, len(b), 2)
    for k, p in enumerate(cands):
        after = model.backend.condition(stance.at(p)).posterior(q).variance.T.reshape(2, len(b), 2)
        one = ((before - after) * region.weight[None, :, None]).sum(1).mean(0) / model.hypers.prior_variance.detach()
        torch.testing.assert_close(mode[k], one.mean(), rtol=1e-6, atol=1e-10)
    assert not torch.allclose(mode, want, rtol=1e-3)  # the draws move the scores: the test can tell them apart


def test_scores_in_chunks_and_the_edge_cases(setup, monkeypatch):
    """Candidates scored a few at a time give the scores of one batch (checked against conditioning the long way
    above); a stroke that never touches scores 0, no candidates give no scores, offsets of the wrong length are
    refused by name."""
    import irft_torch.design.footholds as fh

    stance, model = setup
    region = Region.square(3)
    places = torch.tensor([[0.2, 0.3], [1.2, 0.0]], dtype=F64)
    cands = torch.tensor([[0.3, 0.0], [1.1, 0.1], [0.7, -0.2], [1.6, 0.4], [2.5, 0.0]], dtype=F64)
    whole = foothold_scores(model, stance, cands, places, region)
    monkeypatch.setattr(fh, "SCORE_ELEMENTS", 1)  # one candidate a chunk
    torch.testing.assert_close(foothold_scores(model, stance, cands, places, region), whole, rtol=1e-12, atol=0)
    monkeypatch.undo()
    none = Stance(stance.contacts[:0], stance.offsets[:0])
    assert foothold_scores(model, none, cands, places, region).tolist() == [0.0] * len(cands)
    assert foothold_scores(model, stance, cands[:0], places, region).shape == (0,)
    with pytest.raises(ValueError, match="offsets"):
        Stance(stance.contacts, stance.offsets[:-1])


def test_a_plan_over_the_draws_takes_their_averaged_best(setup, drawn):
    """``plan_footholds(draws=True)``'s first step is the argmax of the draws' averaged scores (checked against each
    draw's conditioning above), its second within reach."""
    stance, model = setup[0], drawn
    cands = torch.tensor([[0.7, 0.0], [0.9, 0.2], [1.0, -0.2], [2.5, 0.0]], dtype=F64)
    roi, region, start = torch.tensor([[1.0, 0.0], [0.4, 0.3]], dtype=F64), Region.square(3), torch.tensor([0.6, 0.0])
    feet = plan_footholds(model, stance, start.to(F64), 2, 0.5, cands, roi, region, draws=True)
    scores = foothold_scores(model, stance, cands[:3], roi, region, draws=True)
    torch.testing.assert_close(feet[0], cands[int(scores.argmax())])
    assert float((feet[1] - feet[0]).norm()) <= 0.5 + 1e-12
