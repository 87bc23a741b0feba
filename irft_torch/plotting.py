"""Figures (matplotlib). Never imported by the core modules.

Every function draws into a given axes (or a new figure) and returns the figure.
"""

from __future__ import annotations

import math

import matplotlib

matplotlib.use("Agg", force=False)
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

__all__ = ["angle_grid", "plot_stress_map", "plot_posterior_map", "plot_toe_path", "plot_coverage", "plot_forces",
           "save"]

P = math.pi


def angle_grid(n: int = 64, dtype=torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    """A regular n x n (beta, gamma) grid over [-pi/2, pi/2]^2 (cell centres), each (n, n)."""
    edges = torch.linspace(-P / 2, P / 2, n + 1, dtype=dtype)
    centres = (edges[1:] + edges[:-1]) / 2
    return torch.meshgrid(centres, centres, indexing="ij")


def _image(ax, values, title, cmap="RdBu_r", symmetric=True, label="N/cm$^3$"):
    v = values.detach().cpu().numpy()
    lim = max(abs(v.min()), abs(v.max()), 1e-12) if symmetric else None
    im = ax.imshow(v.T, origin="lower", extent=(-P / 2, P / 2, -P / 2, P / 2), cmap=cmap,
                   vmin=-lim if symmetric else None, vmax=lim if symmetric else None, aspect="auto")
    ax.set_xlabel(r"$\beta$ (rad)")
    ax.set_ylabel(r"$\gamma$ (rad)")
    ax.set_title(title)
    ax.figure.colorbar(im, ax=ax, label=label)
    return im


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


def plot_posterior_map(model, n: int = 64, title: str = "", points=None):
    """Posterior mean and standard deviation of a fitted model's alpha_x, alpha_z (2 x 2 panels);
    ``points`` (beta, gamma) sequences are marked on every panel (e.g. the sampled angle pairs)."""
    fig, axes = plt.subplots(2, 2, figsize=(11, 8), constrained_layout=True)
    B, G = angle_grid(n)
    post = model.stress_map(B, G)
    for i, name in enumerate("xz"):
        _image(axes[i, 0], post.mean[..., i], f"{title} posterior mean alpha_{name}".strip())
        _image(axes[i, 1], post.stddev[..., i], f"posterior std alpha_{name}", cmap="viridis", symmetric=False)
        for ax in axes[i]:
            for style, (pb, pg) in zip(("k.", "m*"), points or ()):
                ax.plot(pb, pg, style, ms=5 if style == "k." else 9)
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
    for i in idx:
        c, t, L = k.position[i].detach().cpu(), k.tangent[i].detach().cpu(), toe.lengths.cpu()
        a, b = (c - t * L[:, None] / 2) * 100, (c + t * L[:, None] / 2) * 100
        for s0, s1 in zip(a, b):
            ax.plot([s0[0], s1[0]], [s0[1], s1[1]], "r-", lw=2)
    ax.axhline(0.0, color="k", ls="--", lw=1)
    ax.set_xlabel("x (cm)")
    ax.set_ylabel("z (cm)")
    ax.set_aspect("equal")
    return ax.figure


def plot_coverage(contacts, ax=None, title="sampled (beta, gamma)"):
    """Submerged segments' angle pairs in the canonical square."""
    if ax is None:
        fig, ax = plt.subplots(figsize=(4, 4), constrained_layout=True)
    m = contacts.weight_z > 0
    ax.scatter(contacts.beta[m].detach().cpu(), contacts.gamma[m].detach().cpu(), s=3, alpha=0.5)
    ax.set_xlim(-P / 2, P / 2)
    ax.set_ylim(-P / 2, P / 2)
    ax.set_xlabel(r"$\beta$ (rad)")
    ax.set_ylabel(r"$\gamma$ (rad)")
    ax.set_title(title)
    return ax.figure


def plot_forces(time, forces, predicted=None, std=None, axes=None, labels=("measured", "predicted")):
    """F_x and F_z against time (T,), optionally with a prediction and its +-2 std band."""
    if axes is None:
        fig, axes = plt.subplots(2, 1, figsize=(7, 5), sharex=True, constrained_layout=True)
    t = torch.as_tensor(time).detach().cpu()
    for i, name in enumerate(("$F_x$ (N)", "$F_z$ (N)")):
        ax = axes[i]
        ax.plot(t, forces[:, i].detach().cpu(), "k-", lw=1, label=labels[0])
        if predicted is not None:
            p = predicted[:, i].detach().cpu()
            ax.plot(t, p, "C1-", lw=1, label=labels[1])
            if std is not None:
                s = std[:, i].detach().cpu()
                ax.fill_between(t, p - 2 * s, p + 2 * s, color="C1", alpha=0.25)
        ax.set_ylabel(name)
    axes[0].legend()
    axes[-1].set_xlabel("time (s)")
    return axes[0].figure


def save(fig, path) -> None:
    fig.savefig(path, dpi=120)
    plt.close(fig)
