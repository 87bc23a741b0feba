"""Figures (matplotlib). Never imported by the core modules.

Every function draws into given axes (or a new figure) and returns the figure. Importing this
module never changes matplotlib's backend: in Jupyter the figures show inline, in a script they
go wherever the script's backend sends them. Code that only writes files and may run without a
display selects a headless backend itself, in its ``main`` (``matplotlib.use("Agg")``) or with
``MPLBACKEND=Agg`` in the environment, never at import.

Map figures follow one layout: truth | estimate | error (estimate - truth, signed) | posterior
std, one row per axis (alpha_x, alpha_z); truth and estimate share one colour scale per row,
error and std share another (so an error larger than the std it should stay within is visible
at a glance), and the sampled (beta, gamma) pairs are marked on the std panel.
"""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib.pyplot as plt
import torch

__all__ = ["angle_grid", "sampled_angles", "plot_stress_map", "plot_terrain", "plot_map_comparison",
           "plot_posterior_map", "plot_toe_path", "plot_coverage", "plot_forces", "plot_reliability",
           "plot_coverage_cells", "save"]

P = math.pi
UNIT = "N/cm$^3$"


def angle_grid(n: int = 64, dtype=torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    """A regular n x n (beta, gamma) grid over [-pi/2, pi/2]^2 (cell centres), each (n, n).

    Example:
        >>> beta, gamma = angle_grid(48)   # then model.stress_map(beta, gamma)
    """
    edges = torch.linspace(-P / 2, P / 2, n + 1, dtype=dtype)
    centres = (edges[1:] + edges[:-1]) / 2
    B, G = torch.meshgrid(centres, centres, indexing="ij")
    return B, G


def sampled_angles(contacts) -> tuple[torch.Tensor, torch.Tensor]:
    """(beta, gamma), each (K,), of the K segment samples of ``contacts`` that touch the ground."""
    on = (contacts.weight_z != 0) | (contacts.weight_x != 0)
    return contacts.beta[on].detach().cpu(), contacts.gamma[on].detach().cpu()


def _np(v):
    return torch.as_tensor(v).detach().cpu().double().numpy()


def _image(ax, values, title, cmap="RdBu_r", symmetric=True, label=UNIT, vmin=None, vmax=None):
    """One (n, n) map over the canonical square (first index beta, second gamma)."""
    v = _np(values)
    if symmetric and vmin is None and vmax is None:
        lim = max(abs(v.min()), abs(v.max()), 1e-12)
        vmin, vmax = -lim, lim
    im = ax.imshow(v.T, origin="lower", extent=(-P / 2, P / 2, -P / 2, P / 2), cmap=cmap, vmin=vmin, vmax=vmax,
                   aspect="auto", interpolation="nearest")
    ax.set_xlabel(r"$\beta$ (rad)")
    ax.set_ylabel(r"$\gamma$ (rad)")
    ax.set_title(title)
    ax.figure.colorbar(im, ax=ax, label=label)
    return im


def _points(ax, points):
    """Mark point sets: the first as small black dots (sampled pairs), a second as magenta stars."""
    styles = (dict(marker=".", color="k", ms=3, ls="", alpha=0.6, label="sampled"),
              dict(marker="*", color="m", ms=9, ls="", label="held out"))
    for style, (pb, pg) in zip(styles, points or ()):
        ax.plot(_np(pb).ravel(), _np(pg).ravel(), **style)
    ax.set_xlim(-P / 2, P / 2)
    ax.set_ylim(-P / 2, P / 2)


def plot_stress_map(stress_map, n: int = 64, title: str = "", axes=None):
    """alpha_x and alpha_z of any callable (beta, gamma) -> (..., 2) over the canonical square."""
    if axes is None:
        fig, axes = plt.subplots(1, 2, figsize=(10, 4), constrained_layout=True)
    b, g = angle_grid(n)
    with torch.no_grad():
        a = stress_map(b, g)
    _image(axes[0], a[..., 0], rf"{title} $\alpha_x$".strip())
    _image(axes[1], a[..., 1], rf"{title} $\alpha_z$".strip())
    return axes[0].figure


def plot_map_comparison(truth, mean, std, points=None, title: str = "", truth_label: str = "truth", axes=None):
    """truth | estimate | error (estimate - truth, signed) | std, for alpha_x (top) and alpha_z (bottom).

    Args:
        truth: (n, n, 2) map over ``angle_grid(n)`` (N/cm^3).
        mean: (n, n, 2) the estimate, likewise.
        std: (n, n, 2) its posterior standard deviation, likewise.
        points: optional sequence of (beta, gamma) point sets, drawn on the std panel (the first
            as dots: the sampled pairs, e.g. ``sampled_angles(contacts)``; a second as stars).
        truth_label: what the truth is ("truth", "simulated sand", ...).
    Returns:
        the figure (2 x 4 panels).
    """
    if axes is None:
        fig, axes = plt.subplots(2, 4, figsize=(18, 7.5), constrained_layout=True)
    truth, mean, std = (torch.as_tensor(v).detach().cpu().double() for v in (truth, mean, std))
    err = mean - truth
    for i, name in enumerate("xz"):
        lim = float(torch.cat([truth[..., i].abs().flatten(), mean[..., i].abs().flatten()]).max().clamp_min(1e-12))
        elim = float(torch.cat([err[..., i].abs().flatten(), std[..., i].flatten()]).max().clamp_min(1e-12))
        rmse = float(err[..., i].pow(2).mean().sqrt())
        _image(axes[i][0], truth[..., i], rf"{truth_label} $\alpha_{name}$", vmin=-lim, vmax=lim)
        _image(axes[i][1], mean[..., i], rf"estimate (posterior mean) $\alpha_{name}$", vmin=-lim, vmax=lim)
        _image(axes[i][2], err[..., i], rf"error: estimate $-$ {truth_label}, $\alpha_{name}$" + f"\nRMSE {rmse:.3g}",
               cmap="PuOr_r", vmin=-elim, vmax=elim)
        _image(axes[i][3], std[..., i], rf"posterior std $\alpha_{name}$ (same scale as |error|)",
               cmap="viridis", vmin=0.0, vmax=elim)
        _points(axes[i][3], points)
        if points:
            axes[i][3].legend(loc="upper right", fontsize=7, framealpha=0.8)
    if title:
        axes[0][0].figure.suptitle(title)
    return axes[0][0].figure


def plot_posterior_map(model, n: int = 64, title: str = "", points=None, truth=None, truth_label: str = "truth"):
    """A fitted model's maps over ``angle_grid(n)``.

    With ``truth`` (a callable (beta, gamma) -> (..., 2), e.g. the simulated medium): the 2 x 4
    comparison of ``plot_map_comparison``. Without: posterior mean | posterior std (2 x 2).
    ``points`` (a sequence of (beta, gamma) sets) defaults to the model's own sampled angle pairs
    (``model.train_contacts``), marked on every std panel.
    """
    B, G = angle_grid(n)
    post = model.stress_map(B, G)
    mean, std = post.mean.detach(), post.variance.detach().clamp_min(0).sqrt()
    if points is None and getattr(model, "train_contacts", None) is not None:
        points = [sampled_angles(model.train_contacts)]
    if truth is not None:
        with torch.no_grad():
            true = truth(B, G)
        return plot_map_comparison(true, mean, std, points, title, truth_label)
    fig, axes = plt.subplots(2, 2, figsize=(11, 8), constrained_layout=True)
    for i, name in enumerate("xz"):
        _image(axes[i, 0], mean[..., i], rf"{title} posterior mean $\alpha_{name}$".strip())
        _image(axes[i, 1], std[..., i], rf"posterior std $\alpha_{name}$", cmap="viridis", symmetric=False)
        _points(axes[i, 1], points)
        if points:
            axes[i, 1].legend(loc="upper right", fontsize=7, framealpha=0.8)
    return fig


def plot_toe_path(toe, path, n_snapshots: int = 6, ax=None):
    """The toe's path (blue), the toe at a few instants (red), and the surface (dashed)."""
    from .rft.contacts import segment_kinematics

    if ax is None:
        fig, ax = plt.subplots(figsize=(7, 3), constrained_layout=True)
    k = segment_kinematics(toe, path)
    pos = path.position.detach().cpu() * 100
    ax.plot(pos[:, 0], pos[:, 1], "b-", lw=1.5, label="path")
    idx = torch.linspace(0, len(path) - 1, n_snapshots).round().long()
    for j, i in enumerate(idx):
        c, t, L = k.position[i].detach().cpu(), k.tangent[i].detach().cpu(), toe.lengths.cpu()
        a, b = (c - t * L[:, None] / 2) * 100, (c + t * L[:, None] / 2) * 100
        for s, (s0, s1) in enumerate(zip(a, b)):
            ax.plot([s0[0], s1[0]], [s0[1], s1[1]], "r-", lw=2, label="toe" if j == 0 and s == 0 else None)
    ax.axhline(0.0, color="k", ls="--", lw=1, label="surface")
    ax.set_xlabel("x (cm)")
    ax.set_ylabel("z (cm)")
    ax.set_aspect("equal")
    return ax.figure


def plot_coverage(contacts, ax=None, title="sampled (beta, gamma)"):
    """Submerged segments' angle pairs in the canonical square."""
    if ax is None:
        fig, ax = plt.subplots(figsize=(4, 4), constrained_layout=True)
    b, g = sampled_angles(contacts)
    ax.scatter(b, g, s=3, alpha=0.5)
    ax.set_xlim(-P / 2, P / 2)
    ax.set_ylim(-P / 2, P / 2)
    ax.set_xlabel(r"$\beta$ (rad)")
    ax.set_ylabel(r"$\gamma$ (rad)")
    ax.set_title(title)
    return ax.figure


def plot_forces(time, forces, predicted=None, std=None, axes=None, labels=None, band_label=None):
    """F_x and F_z in N against the time since the first sample, in s.

    With a prediction and its std (and no ``axes`` given), each force panel gets a residual panel
    below it: data - prediction with the +-2 std band around zero, which stays visible however
    small the band is next to the force's range, and the share of samples inside it.

    Args:
        time: (T,) sample times in s; any origin (epoch seconds included): the axis starts at 0.
        forces: (T, 2) the forces to show.
        predicted: optional (T, 2) prediction, drawn over them, with
        std: its (T, 2) standard deviation, drawn as a shaded, outlined +-2 std band.
        axes: optional two axes (F_x, F_z) to draw into (then no residual panels).
        labels: (forces label, prediction label). Defaults: ("force", ...) alone, ("data",
            "I-RFT prediction") with a prediction; say "measured" only for measured forces.
        band_label: what the band is. To compare with data, pass the std of a new measurement
            (``model.predict_forces(c, include_noise=True)``): about 95 % of the samples should then
            lie inside; the std of the mean force alone is narrower.
    Returns:
        the figure; its first two axes are the F_x and F_z panels.
    """
    if labels is None:
        labels = ("data", "I-RFT prediction") if predicted is not None else ("force", "")
    if band_label is None:
        band_label = r"$\pm 2\sigma$ band"
    residuals = axes is None and predicted is not None and std is not None
    if axes is None and residuals:
        fig = plt.figure(figsize=(8, 7.5), constrained_layout=True)
        gs = fig.add_gridspec(4, 1, height_ratios=(3, 1.3, 3, 1.3))
        axes = [fig.add_subplot(gs[0]), fig.add_subplot(gs[2])]
        res_axes = [fig.add_subplot(gs[1], sharex=axes[0]), fig.add_subplot(gs[3], sharex=axes[0])]
    elif axes is None:
        fig, axes = plt.subplots(2, 1, figsize=(8, 5.5), sharex=True, constrained_layout=True)
    t = torch.as_tensor(time).detach().cpu().double()
    t = t - t[0]
    for i, name in enumerate(("x", "z")):
        ax = axes[i]
        y = torch.as_tensor(forces[:, i]).detach().cpu().double()
        ax.plot(t, y, "k-", lw=1, label=labels[0])
        if predicted is not None:
            p = torch.as_tensor(predicted[:, i]).detach().cpu().double()
            ax.plot(t, p, "C1-", lw=1.2, label=labels[1])
            if std is not None:
                s = torch.as_tensor(std[:, i]).detach().cpu().double()
                ax.fill_between(t, p - 2 * s, p + 2 * s, color="C1", alpha=0.35, lw=0,
                                label=band_label)
                ax.plot(t, p - 2 * s, color="C1", lw=0.6, ls=":")
                ax.plot(t, p + 2 * s, color="C1", lw=0.6, ls=":")
                if residuals:
                    r, rax = y - p, res_axes[i]
                    ok = torch.isfinite(r) & torch.isfinite(s)
                    inside = float(((r.abs() <= 2 * s) & ok).sum()) / max(int(ok.sum()), 1)
                    rax.fill_between(t, -2 * s, 2 * s, color="C1", alpha=0.35, lw=0,
                                     label=f"{band_label} ({100 * inside:.0f} % of samples inside)")
                    rax.plot(t, r, "k-", lw=0.7, label=f"{labels[0]} $-$ prediction")
                    rax.axhline(0.0, color="C1", lw=0.8)
                    rax.set_ylabel(rf"$F_{name}$ residual (N)")
                    rax.grid(alpha=0.3)
                    rax.legend(fontsize=7, loc="upper right")
        ax.set_ylabel(rf"$F_{name}$ (N)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="best")
    (res_axes if residuals else axes)[-1].set_xlabel("time since the first sample (s)")
    return axes[0].figure


def plot_terrain(field, extent, footholds=None, n: int = 120, axes=None):
    """A ``rft.TerrainField`` over the ground: alpha_z of a plate pushed straight down (beta 0, gamma 90 deg)
    and alpha_x of a plate dragged forward (beta 0, gamma 0), N/cm^3, over ``extent`` = (x_min, x_max, y_min,
    y_max) m, with the ``footholds`` (N, 2) m where given. Returns the figure (2 panels)."""
    import math

    x0, x1, y0, y1 = (float(v) for v in extent)
    if axes is None:
        tall = 1.6 + 5.0 * (y1 - y0) / max(x1 - x0, 1e-12)
        fig, axes = plt.subplots(1, 2, figsize=(12, min(max(tall, 2.6), 6.0)), constrained_layout=True)
    xs = torch.linspace(x0, x1, n, dtype=torch.float64)
    ys = torch.linspace(y0, y1, max(2, int(n * (y1 - y0) / max(x1 - x0, 1e-12))), dtype=torch.float64)
    s = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), dim=-1)  # (ny, nx, 2)
    zero = torch.zeros(s.shape[:-1], dtype=torch.float64)
    with torch.no_grad():
        down = field(zero, zero + math.pi / 2, s)[..., 1]  # gamma positive downward (docs/conventions.md)
        drag = field(zero, zero, s)[..., 0]
    for ax, v, title in ((axes[0], down, "$\\alpha_z$ of a flat plate pushed down\n($\\beta$ 0, $\\gamma$ 90°)"),
                         (axes[1], drag, "$\\alpha_x$ of a flat plate dragged forward\n($\\beta$ 0, $\\gamma$ 0)")):
        im = ax.imshow(_np(v), origin="lower", extent=(x0, x1, y0, y1), cmap="viridis", aspect="equal")
        ax.figure.colorbar(im, ax=ax, label=UNIT, fraction=0.046 * (y1 - y0) / max(x1 - x0, 1e-12) * 2, pad=0.02)
        if footholds is not None:
            p = _np(torch.as_tensor(footholds))
            ax.plot(p[:, 0], p[:, 1], "w^", ms=6, mec="k", label="footholds")
            ax.legend(loc="upper right", fontsize=8)
        ax.set(title=title, xlabel="x (m)", ylabel="y (m)")
    axes[0].figure.suptitle(field.name)
    return axes[0].figure


def save(fig, path) -> None:
    """Write ``fig`` (PNG, 120 dpi; the format follows the suffix) and close it; written to a temporary
    file and renamed into place (``_files.atomic_path``), so a failed write leaves the old figure."""
    from ._files import atomic_path

    try:
        with atomic_path(path, "figure") as tmp:
            fig.savefig(tmp, dpi=120, format=Path(path).suffix.lstrip(".") or "png")
    finally:
        plt.close(fig)


def plot_coverage_cells(observed: dict, calibrated: dict, band=(0.85, 0.99), level: float = 0.95, ax=None,
                        title: str = "coverage per cell against a calibrated model"):
    """Each cell's observed coverage of the central ``level`` interval (a dot) against the coverages a
    perfectly calibrated model gives for that cell (its central 90 % as a bar, median a tick), with
    ``band`` shaded: whether a cell outside the band is a miscalibration or the scatter a calibrated
    model shows too.

    Args:
        observed: {cell label: observed coverage (0-1)}.
        calibrated: {cell label: (draws,) coverages of truths the model is calibrated for (0-1)}.
    """
    import numpy as np

    from . import metrics

    if ax is None:
        fig, ax = plt.subplots(figsize=(max(7.0, 0.34 * len(observed) + 2.5) + 3.2, 5.0), constrained_layout=True)
    ax.axhspan(100 * band[0], 100 * band[1], color="tab:green", alpha=0.12,
               label=f"band {100 * band[0]:.0f}-{100 * band[1]:.0f} %")
    ax.axhline(100 * level, color="k", ls="--", lw=0.8, label=f"nominal {100 * level:.0f} %")
    x = np.arange(len(observed))
    for i, label in enumerate(observed):
        c = np.asarray(calibrated[label], dtype=float) * 100
        lo, mid, hi = np.percentile(c, [5, 50, 95])
        pit = float(metrics.percentile_among(observed[label], calibrated[label]))
        ax.plot([i, i], [lo, hi], color="0.6", lw=5, solid_capstyle="butt",
                label="calibrated model: 5-95 % of its coverages" if i == 0 else None)
        ax.plot([i - 0.25, i + 0.25], [mid, mid], color="0.3", lw=1.2,
                label="calibrated model: median" if i == 0 else None)
        inside = 0.025 <= pit <= 0.975
        ax.plot(i, 100 * observed[label], "o", ms=6, color="tab:blue" if inside else "tab:red",
                label=None)
    ax.plot([], [], "o", color="tab:blue", label="observed, within the calibrated model's central 95 %")
    ax.plot([], [], "o", color="tab:red", label="observed, outside it")
    ax.set_xticks(x)
    ax.set_xticklabels(list(observed), rotation=60, ha="right", fontsize=7)
    ax.set_xlim(-0.7, len(observed) - 0.3)
    ax.set_ylabel(f"share of the truth inside the central {100 * level:.0f} % interval (%)")
    ax.set_title(title)
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # outside: the bars fill the axes
    return ax.figure


def plot_reliability(observed: dict, levels, ax=None, title: str = "reliability"):
    """Reliability diagram: for each central posterior interval (nominal level, x) the share of the
    truth inside it (observed, y); the diagonal is perfect calibration, below it overconfident.

    Args:
        observed: {label: [share inside at each level]} (0-1), one line per label.
        levels: the nominal levels (0-1), e.g. (0.5, 0.9, 0.95).
    """
    if ax is None:
        fig, ax = plt.subplots(figsize=(7.5, 6.5), constrained_layout=True)
    lv = [100 * float(v) for v in levels]
    ax.plot([0, 100], [0, 100], "k--", lw=1, label="calibrated (observed = nominal)")
    many = len(observed) > 10
    colors = plt.get_cmap("tab20" if many else "tab10").colors  # type: ignore[attr-defined]  # a ListedColormap
    for i, (label, shares) in enumerate(observed.items()):  # beyond the palette: another marker, never a repeat
        ax.plot(lv, [100 * float(v) for v in shares], "-", marker="os^Dv"[(i // len(colors)) % 5],
                lw=0.8 if many else 1.5, ms=3.5 if many else 5, alpha=0.75 if many else 1.0,
                color=colors[i % len(colors)], label=label)
    ax.set_xlim(40, 100)
    ax.set_ylim(0, 101)
    ax.set_xlabel("nominal level of the central posterior interval (%)")
    ax.set_ylabel("share of the truth inside the interval (%)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=6 if many else 8, loc="lower right", ncol=2 if many else 1)
    return ax.figure
