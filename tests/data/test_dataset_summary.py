"""data.dataset_summary: the time in contact counts no gap (was: a one-day hole in a log counted a day
of contact)."""

import torch

from irft_torch import rft
from irft_torch.data import Dataset, dataset_summary


def test_a_gap_is_not_time_in_contact():
    """Two stretches of 11 samples 10 ms apart, all in contact, a day between them: by hand 2 x 0.10 s
    of steps plus the step over the gap counted as 3 intervals, 0.23 s (the duration says the day)."""
    c = rft.contacts(rft.IToe(0.02, 0.008), rft.rectangle_path(n_steps=22))
    c = rft.Contacts(c.beta, c.gamma, torch.full_like(c.weight_x, -1.0), torch.ones_like(c.weight_z))
    t = torch.cat([torch.arange(11) * 0.01, 86400 + torch.arange(11) * 0.01])
    ds = Dataset(c, torch.ones(22, 2), t, torch.zeros(22, 2))
    lines = dataset_summary(ds)
    assert lines[0].startswith("duration 86400.10 s") and lines[1].startswith("in contact 0.23 s (100 % of samples)")
