"""Physical hyperparameter priors of 3-D I-RFT: the planar model's (``gp.kernels.priors``, its docstring gives the
reasons) with the third map added.

- outputscale of map c: centre max(zeta rms_c, s_c, 0.5 rms_c max_c' s_c' / rms_c')^2, zeta the medium's
  least-squares scale of the generic map on all three force axes (3-D RFT with alpha_y = alpha_x(0, 0), the
  rover-wheel authors' form), rms_c the generic map's rms over the square per unit zeta (alpha_x 0.209,
  alpha_y 0.136: the constant, alpha_z 0.381), s_c the data's own stress per depth of map c; log-sd ln 2;
- lengthscales: centre 1.5, log-sd 1.5 (as planar);
- noise of each axis: centre 1e-2 of its mean squared force (floored), log-sd ln 10;
- Li et al.'s term (``kernel="li"``): its variance per map has the outputscale's centre and width (as planar).

Here: the centres; ``gp.kernels.priors.register_physical_priors`` (which takes K maps) registers them.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ...rft.contacts3d import Contacts3D
from ...rft.forces3d import forces_3d
from ...rft.stress_maps import FourierStressMap
from ..kernels.priors import GENERIC_RMS, JOINT_FRACTION, LENGTHSCALE_CENTRE, NOISE_RELATIVE

__all__ = ["GENERIC_RMS_3D", "data_scales_3d", "prior_centres_3d"]

GENERIC_RMS_3D = (GENERIC_RMS[0], 0.136, GENERIC_RMS[1])  # alpha_x, alpha_y (= alpha_x(0, 0)), alpha_z


def data_scales_3d(c: Contacts3D, f: Tensor) -> tuple[Tensor, Tensor]:
    """The data's force scale (3,) N (rms per axis) and stress-per-depth scale (3,) N/cm^3 per map: the rms of
    the forces the map feeds over the rms of its summed |weights| (a map no force sees takes alpha_x's)."""
    fs = f.pow(2).mean(0).sqrt().clamp_min(1e-300)
    fxy = f[:, :2].pow(2).sum(-1).mean().sqrt()

    def per_map(w):
        s = w.abs().sum(1).pow(2).sum(-1).mean().sqrt() if w.ndim == 3 else w.abs().sum(1).pow(2).mean().sqrt()
        return s

    sx, sy, sz = per_map(c.weight_x), per_map(c.weight_y), per_map(c.weight_z)
    mx = fxy / sx.clamp_min(1e-300)
    my = fxy / sy if float(sy) > 0 else mx
    mz = fs[2] / sz.clamp_min(1e-300)
    return fs, torch.stack([mx, my, mz]).clamp_min(1e-300)


def medium_scale_3d(c: Contacts3D, f: Tensor) -> float:
    """Least-squares zeta of the generic map (alpha_y = alpha_x(0, 0)) on all three axes; 0 if it does not
    project positively."""
    g = forces_3d(FourierStressMap.generic().to(c.beta.dtype), c)
    den = float(g.pow(2).sum())
    return max(float((f * g).sum()) / den, 0.0) if den > 0 else 0.0


def prior_centres_3d(c: Contacts3D, f: Tensor, map_scale: Tensor, noise_floor: float) -> dict:
    rms = torch.tensor(GENERIC_RMS_3D, dtype=f.dtype, device=f.device)
    ms = map_scale.to(rms)
    fallback = float((ms / rms).max())
    zeta = max(medium_scale_3d(c, f), 0.1 * fallback)
    sigma = torch.maximum(torch.maximum(zeta * rms, ms), JOINT_FRACTION * fallback * rms)
    noise = (NOISE_RELATIVE * f.pow(2).mean(0)).clamp_min(noise_floor * 10)
    return {"zeta": zeta, "outputscale": sigma.pow(2), "lengthscale": LENGTHSCALE_CENTRE, "noise": noise}
