"""Figures: what they show is checked on the drawn artists against values built here."""

import math

import matplotlib
import numpy as np
import torch
from matplotlib.collections import PolyCollection

from irft_torch import plotting


def test_force_plot_time_axis_starts_at_zero_and_band_is_visible_and_labelled():
    t = 1.7e9 + torch.linspace(0, 20, 201, dtype=torch.float64)  # epoch seconds, as a CAN log gives them
    base = torch.stack([torch.sin(t - 1.7e9), 5 + torch.cos(t - 1.7e9)], -1)
    pred, std = base + 0.01, torch.full_like(base, 0.05)
    fig = plotting.plot_forces(t, base, pred, std)
    fx, fz = fig.axes[:2]
    for ax, name in ((fx, "F_x"), (fz, "F_z")):
        x = ax.get_lines()[0].get_xdata()
        assert x[0] == 0.0 and abs(x[-1] - 20.0) < 1e-9  # relative to the first sample, not "+1.7e9"
        assert ax.get_xlim()[1] < 100
        assert name in ax.get_ylabel() and "(N)" in ax.get_ylabel()
        bands = [c for c in ax.collections if isinstance(c, PolyCollection)]
        assert len(bands) == 1 and bands[0].get_alpha() >= 0.3
        assert "2" in bands[0].get_label() and "sigma" in bands[0].get_label()
        # the band spans prediction +- 2 std
        ys = np.concatenate([p.vertices[:, 1] for p in bands[0].get_paths()])
        i = 0 if name == "F_x" else 1
        assert math.isclose(ys.max(), float((pred[:, i] + 0.1).max()), rel_tol=1e-6)
        legend = ax.get_legend()
        assert legend is not None and {"data", "I-RFT prediction"} <= {x.get_text() for x in legend.get_texts()}
    # residual panels: data - prediction (= -0.01 everywhere) inside the band, the share said in the legend
    res = fig.axes[2:]
    assert len(res) == 2
    r = res[0].get_lines()[0].get_ydata()
    assert np.allclose(r, -0.01)
    assert "100 % of samples inside" in " ".join(x.get_text() for x in res[0].get_legend().get_texts())
    assert "time since the first sample (s)" == res[-1].get_xlabel()
    matplotlib.pyplot.close(fig)


def test_force_plot_without_a_prediction_is_not_called_measured():
    f = torch.zeros(10, 2)
    fig = plotting.plot_forces(torch.arange(10.0), f)
    texts = [x.get_text() for ax in fig.axes[:2] for x in ax.get_legend().get_texts()]
    assert "measured" not in " ".join(texts)
    matplotlib.pyplot.close(fig)


def test_map_comparison_panels_signed_error_shared_scales_and_points():
    n = 6
    B, G = plotting.angle_grid(n)
    truth = torch.stack([B, G], -1)
    mean = truth + torch.stack([0.1 * torch.ones_like(B), -0.2 * torch.ones_like(G)], -1)
    std = torch.full_like(truth, 0.05)
    points = (torch.tensor([0.1, 0.2]), torch.tensor([-0.3, 0.4]))
    fig = plotting.plot_map_comparison(truth, mean, std, [points])
    axes = [ax for ax in fig.axes if ax.images]  # the 8 map panels (not the colorbars)
    assert len(axes) == 8
    for row, expected_err in ((0, 0.1), (1, -0.2)):
        t_ax, m_ax, e_ax, s_ax = axes[4 * row: 4 * row + 4]
        assert "truth" in t_ax.get_title() and "estimate" in m_ax.get_title()
        assert "error" in e_ax.get_title() and "std" in s_ax.get_title()
        err = e_ax.images[0].get_array()
        assert np.allclose(err, expected_err)  # estimate - truth, signed
        assert t_ax.images[0].get_clim() == m_ax.images[0].get_clim()  # truth and estimate: one scale
        assert np.allclose(e_ax.images[0].get_clim(), (-abs(expected_err), abs(expected_err)))
        assert np.allclose(s_ax.images[0].get_clim(), (0.0, abs(expected_err)))  # std on the |error| scale
        xs = [line.get_xdata() for line in s_ax.get_lines()]
        assert any(np.allclose(x, [0.1, 0.2]) for x in xs)  # sampled points on the std panel
    matplotlib.pyplot.close(fig)


def test_coverage_cells_marks_observations_outside_the_calibrated_range():
    # cell a: calibrated coverages 0.80-0.99 (uniform), observed 0.90: inside; cell b: the same, observed 0.70: below
    # everything a calibrated model gives, so drawn red; the bars span the 5-95th percentiles computed here
    cal = torch.linspace(0.80, 0.99, 201, dtype=torch.float64)
    fig = plotting.plot_coverage_cells({"a": 0.90, "b": 0.70}, {"a": cal, "b": cal})
    ax = fig.axes[0]
    dots = [ln for ln in ax.get_lines() if ln.get_marker() == "o" and len(ln.get_xdata())]
    assert [(float(d.get_xdata()[0]), float(d.get_ydata()[0])) for d in dots] == [(0.0, 90.0), (1.0, 70.0)]
    assert matplotlib.colors.same_color(dots[0].get_color(), "tab:blue")
    assert matplotlib.colors.same_color(dots[1].get_color(), "tab:red")
    bars = [ln for ln in ax.get_lines() if ln.get_linewidth() == 5]
    lo, hi = np.percentile(cal.numpy() * 100, [5, 95])
    np.testing.assert_allclose(bars[0].get_ydata(), [lo, hi])
    labels = ax.get_legend_handles_labels()[1]
    assert "band 85-99 %" in labels and any("calibrated model" in x for x in labels)
