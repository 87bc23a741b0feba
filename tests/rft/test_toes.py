import math

import pytest
import torch

from irft_torch.rft import CToe, IToe, PolylineToe


def test_itoe_segments():
    toe = IToe(length=0.02, width=0.008, n_segments=4)
    torch.testing.assert_close(toe.lengths, torch.full((4,), 0.005))
    torch.testing.assert_close(toe.centres[:, 0], torch.tensor([-0.0075, -0.0025, 0.0025, 0.0075]))
    torch.testing.assert_close(toe.tangents, torch.tensor([[1.0, 0.0]] * 4))
    tilted = IToe(0.02, 0.008, tilt=math.pi / 6, n_segments=2)
    torch.testing.assert_close(tilted.tangents[0], torch.tensor([math.cos(math.pi / 6), math.sin(math.pi / 6)]))


def test_ctoe_geometry_by_hand():
    R, M = 0.02, 10
    toe = CToe(radius=R, width=0.008, n_segments=M)
    chord = 2 * R * math.sin(math.pi / (2 * M))
    torch.testing.assert_close(toe.lengths, torch.full((M,), chord))
    # opening up: the arc's mid-point is the origin and the lowest point; ends at (+-R, R)
    assert toe.centres[:, 1].min() > 0
    ends = torch.tensor([[-R, R], [R, R]])
    first = toe.centres[0] - toe.tangents[0] * toe.lengths[0] / 2
    last = toe.centres[-1] + toe.tangents[-1] * toe.lengths[-1] / 2
    torch.testing.assert_close(torch.stack([first, last]), ends)
    # tilts span (-pi/2, pi/2): the C-toe samples the whole beta range
    beta = torch.atan2(toe.tangents[:, 1], toe.tangents[:, 0])
    assert beta.min() < -1.3 and beta.max() > 1.3


@pytest.mark.parametrize("opening", ["up", "down", "left", "right"])
def test_ctoe_openings_are_rotations(opening):
    toe = CToe(0.03, 0.01, 6, opening=opening)
    torch.testing.assert_close(toe.centres.norm(dim=1).sort().values,
                               CToe(0.03, 0.01, 6).centres.norm(dim=1).sort().values)


def test_polyline_resampling():
    toe = PolylineToe([(0, 0), (0.03, 0), (0.03, 0.01)], width=0.01, n_segments=4)
    torch.testing.assert_close(toe.lengths.sum(), torch.tensor(0.04), atol=1e-3, rtol=0)
    raw = PolylineToe([(0, 0), (0.03, 0), (0.03, 0.01)], width=0.01)
    assert raw.n_segments == 2


def test_bad_toes():
    with pytest.raises(ValueError, match="n_segments"):
        IToe(0.02, 0.008, n_segments=0)
    with pytest.raises(ValueError, match="length"):
        IToe(-0.02, 0.008)
    with pytest.raises(ValueError, match="radius"):
        CToe(float("nan"), 0.008)
    with pytest.raises(ValueError, match="opening"):
        CToe(0.02, 0.008, opening="sideways")
    with pytest.raises(ValueError, match="points"):
        PolylineToe([(0, 0)], 0.01)
    with pytest.warns(UserWarning, match="millimetres"):
        CToe(radius=20.0, width=0.008)


def test_tilt_in_degrees_warns_and_nan_is_an_error():
    """IToe(tilt=30) is 30 rad, almost surely 30 degrees meant: a warning that says so; NaN: an error."""
    with pytest.warns(UserWarning, match=r"tilt=30.0 rad .*degrees\? 30.0 deg = 0.5236 rad"):
        IToe(0.02, 0.008, tilt=30)
    with pytest.raises(ValueError, match="tilt must be a finite angle"):
        IToe(0.02, 0.008, tilt=float("nan"))
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        toe = IToe(0.02, 0.008, tilt=-math.pi / 3)  # radians: silent
    assert toe.tangents[0].tolist() == pytest.approx([0.5, -math.sqrt(3) / 2])
