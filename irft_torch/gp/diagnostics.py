"""What a fit can and cannot say: per map, how much of the square the forces constrain, which
lengthscales the data cannot inform, and whether the signal collapsed below the noise.

    report = model.diagnostics()
    print(report)            # plain words, one paragraph per map
    report.maps[0].constrained_fraction
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from ..rft.contacts import Contacts
from .kernels.embedding import embed_angles

__all__ = ["MapDiagnostics", "Diagnostics", "diagnose"]

EMBEDDING = ("sin 2beta", "cos 2beta", "sin gamma", "cos gamma")
AXES = ("alpha_x", "alpha_z")


@dataclass
class MapDiagnostics:
    """One map's report.

    Attributes:
        name: "alpha_x" or "alpha_z".
        constrained_fraction: share of a 24 x 24 grid over the canonical square where the posterior
            variance is below half the prior variance (the data decide there, not the prior).
        variance_ratio: mean posterior-to-prior variance ratio over that grid (1: nothing learned).
        uninformed_lengthscales: embedding dimensions the training segments never vary (std of that
            coordinate below 1e-3): the likelihood cannot move their lengthscales, whose initial
            value alone sets how the map extrapolates along them.
        signal_to_noise: prior force signal variance (the prior map variance, ``hypers.prior_variance``: the
            outputscale, plus Li et al.'s v with ``kernel="li"`` and u mean(g^2) with ``kernel="li+generic"``,
            x the mean squared weight sum) over
            the noise variance; below 1 the outputscale has collapsed below what the noise resolves
            (the whole map's prior signal is smaller than one sample's noise).
        unidentified: no part of the square constrained, or a collapsed signal.
    """

    name: str
    constrained_fraction: float
    variance_ratio: float
    uninformed_lengthscales: list[str] = field(default_factory=list)
    signal_to_noise: float = math.inf
    unidentified: bool = False

    def __str__(self) -> str:
        words = [f"{self.name}: the forces constrain {100 * self.constrained_fraction:.0f} % of the square "
                 f"(posterior variance below half the prior's; mean posterior/prior variance "
                 f"{self.variance_ratio:.2f}); signal-to-noise {self.signal_to_noise:.3g}."]
        if self.uninformed_lengthscales:
            words.append(f"The data never vary {', '.join(self.uninformed_lengthscales)}: those lengthscales keep "
                         f"their initial value, which alone sets how the map extrapolates along them.")
        if self.signal_to_noise < 1:
            words.append("Its prior variance collapsed below what the force noise can resolve.")
        if self.unidentified:
            words.append(f"{self.name} is not constrained by these forces: its posterior is the prior "
                         f"(treat its values as unknown).")
        return " ".join(words)


@dataclass
class Diagnostics:
    maps: list[MapDiagnostics]
    notes: list[str] = field(default_factory=list)  # about the fit as a whole (the hyperparameter draws)

    def __str__(self) -> str:
        return "\n".join([*(str(m) for m in self.maps), *self.notes])

    @property
    def unidentified(self) -> list[str]:
        return [m.name for m in self.maps if m.unidentified]


def diagnose(model, n: int = 24) -> Diagnostics:
    """The report for a fitted ``InverseRFT`` (see ``MapDiagnostics``)."""
    e = torch.linspace(-math.pi / 2, math.pi / 2, n + 1, dtype=model.dtype, device=model._device)
    c = (e[1:] + e[:-1]) / 2
    B, G = torch.meshgrid(c, c, indexing="ij")
    with torch.no_grad():
        var = model.stress_map(B, G).variance.reshape(-1, 2)  # (n^2, 2)
        prior = model.hypers.prior_variance.detach()  # (2,): with Li et al.'s term, s + v (+ u mean g^2)
        prior_at = model.hypers.prior_variance_at(B, G).detach().reshape(-1, 2)  # (n^2, 2): the same pointwise
        noise = model.hypers.noise.detach()
        tc: Contacts = model.train_contacts
        scale = model.noise_scale
        w = torch.stack([(tc.weight_x * scale[:, :1]).abs().sum(-1), (tc.weight_z * scale[:, 1:]).sum(-1)])
        active = (tc.weight_x != 0) | (tc.weight_z != 0)
        phi = embed_angles(tc.beta[active], tc.gamma[active])  # (S, 4)
        spread = phi.std(0) if phi.shape[0] > 1 else torch.zeros(4, dtype=phi.dtype)
        # signal variance of a typical sample vs its noise (both in N^2, measured units)
        snr = prior * w.pow(2).mean(-1) / (noise * scale.pow(2).mean(0))
    out = []
    for a in range(2):
        ratio = (var[:, a] / prior_at[:, a]).clamp(0, 1)
        frac = float((ratio < 0.5).double().mean())
        flat = [EMBEDDING[d] for d in range(4) if float(spread[d]) < 1e-3]
        s = float(snr[a])
        out.append(MapDiagnostics(AXES[a], frac, float(ratio.mean()), flat, s, frac == 0.0 or s < 1.0))
    hp = getattr(model, "hyper_posterior", None)
    notes = [f"Hyperparameter draws: {hp.extra['truncated']}."] if hp is not None and "truncated" in hp.extra else []
    err, tol = float(model.truncation_error().max()), getattr(model.backend, "tol", None)
    if err > 0:  # an approximate kernel (the spectral basis): its error, and whether it is within the model's tol
        within = "" if tol is None else f", within tol {tol:.0e}" if err <= tol else f", ABOVE tol {tol:.0e}"
        notes.insert(0, f"Kernel: {model.backend.describe()}{within}.")
    return Diagnostics(out, notes)
