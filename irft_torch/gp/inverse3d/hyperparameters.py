"""Hyperparameters of 3-D I-RFT: three maps (alpha_x, alpha_y, alpha_z), three force-noise variances, and
how the model's covariance splits into two independent blocks.

The blocks (docs/inverse3d.md): F_z sees alpha_z only; F_x and F_y both see alpha_x (through the element's
in-plane direction u) and alpha_y (through e1). So the force covariance is block diagonal,

    horizontal (rows F_x then F_y, 2T):  sum_{c in x, y} W_hc K_c W_hc^T + diag(sigma_x^2 I, sigma_y^2 I)
    vertical   (rows F_z, T):            W_z K_z W_z^T + sigma_z^2 I

and the planar model is the special case where the F_y rows see no map (they add only their own noise
term). alpha_y is either a third map over (beta, gamma) (an ARD RBF on the embedding, like the others) or
a constant with a zero-mean normal prior of variance s_y (a rank-one kernel term s_y (W_y 1)(W_y 1)^T).
With ``kernel="li"`` each map over (beta, gamma) also has Li et al.'s rank-9 term v_c f(theta) . f(theta')
(``gp.kernels.li_basis``; not a constant alpha_y).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from gpytorch.constraints import GreaterThan
from gpytorch.likelihoods import GaussianLikelihood
from torch import Tensor

from ..kernels.angle import AngleKernel
from ..kernels.constraints import ScaledGreaterThan
from ..kernels.hyperparameters import MapHyperparameters
from ..kernels.li_basis import LiBasisVariance

__all__ = ["Block", "BLOCKS", "MAPS", "AXES", "ALPHA_Y", "LENGTHSCALE_FLOOR_3D", "RFT3DHyperparameters"]

MAPS = ("alpha_x", "alpha_y", "alpha_z")
AXES = ("F_x", "F_y", "F_z")
ALPHA_Y = ("map", "constant")
# The shortest lengthscale a 3-D map may take (embedding units; the planar model's floor is 0.05). Two reasons,
# neither from the wheels: an ARD RBF fitted to the DEM plate intrusion's 54 measured stresses (an independent
# granular simulation) takes 0.23-2.9, Li et al.'s generic map 2.2-5.4, so no medium measured has finer features;
# and above 0.21 the spectral basis's 30 harmonics per angle hold the RBF within tol 1e-7 whatever the other
# lengthscales (the bound, ``kernels.fourier``: 9.3e-8 at the worst), so the default fit is never truncated by the
# cap. Without it, the wheels' aggregate forces drive alpha_x's sin 2beta lengthscale onto 0.05
# (experiments/notes/wheel3d_lengthscales.md).
LENGTHSCALE_FLOOR_3D = 0.21


@dataclass(frozen=True)
class Block:
    """One independent block of the force covariance: the maps it sees and the force axes of its rows (each
    axis a group of T rows, in this order, with its own noise variance)."""

    name: str
    maps: tuple[int, ...]
    axes: tuple[int, ...]


BLOCKS = (Block("horizontal", (0, 1), (0, 1)), Block("vertical", (2,), (2,)))


class RFT3DHyperparameters(MapHyperparameters):
    """Kernel of the three maps (``AngleKernel`` with batch (3,): lengthscale (3, 1, 4), outputscale (3,) in
    (N/cm^3)^2) and the noise of the three force axes (a batched gpytorch ``GaussianLikelihood``, (3,) N^2).

    With ``alpha_y="constant"`` only the alpha_y outputscale is used for that map (the prior variance of the
    constant); its lengthscale has no gradient and stays where it is. ``li_basis``: ``li``, a
    ``LiBasisVariance`` (3,) (N/cm^3)^2 of Li et al.'s term per map (alpha_y's unused when it is a constant).
    ``lengthscale_floor``: every lengthscale is above it (``LENGTHSCALE_FLOOR_3D``; the constraint's buffer, so a model
    file from before it was raised loads with its own, 0.05).
    """

    n_maps = 3

    def __init__(self, alpha_y: str = "map", noise_floor: float = 1e-6, force_scale=1.0, map_scale=1.0,
                 li_basis: bool = False, lengthscale_floor: float = LENGTHSCALE_FLOOR_3D) -> None:
        super().__init__()
        if alpha_y not in ALPHA_Y:
            raise ValueError(f"alpha_y must be one of {ALPHA_Y}, got {alpha_y!r}")
        self.alpha_y = alpha_y
        fs = torch.as_tensor(force_scale, dtype=torch.get_default_dtype()).expand(3)
        ms = torch.as_tensor(map_scale, dtype=torch.get_default_dtype()).expand(3)
        self.kernel = AngleKernel(batch_shape=torch.Size([3]), lengthscale_constraint=GreaterThan(lengthscale_floor),
                                  outputscale_constraint=ScaledGreaterThan(0.0, ms.pow(2)))
        self.likelihood = GaussianLikelihood(batch_shape=torch.Size([3]),
                                             noise_constraint=ScaledGreaterThan(noise_floor, fs.pow(2).reshape(3, 1)))
        self.li = LiBasisVariance(scale=ms.pow(2), n_maps=3) if li_basis else None

    @property
    def lengthscale_floor(self) -> float:
        """The lengthscales' lower bound (the constraint's buffer: a state dict, hence a model file, carries it)."""
        return float(self.kernel.base_kernel.raw_lengthscale_constraint.lower_bound)

    def li_of(self, c: int, detach: bool) -> Tensor | None:
        """() map c's Li et al.'s variance, or None (no term, or a constant alpha_y)."""
        if self.li is None or self.constant_map(c):
            return None
        v = self.li.variance[c]
        return v.detach() if detach else v

    @property
    def prior_variance(self) -> Tensor:
        """(3,) each map's prior variance at any angle pair, (N/cm^3)^2: the outputscale, plus Li et al.'s v where
        the map has the term (|f(theta)|^2 = 1, ``gp.kernels.li_basis``)."""
        s = self.outputscale
        if self.li is None:
            return s
        keep = torch.tensor([not self.constant_map(c) for c in range(3)], device=s.device)
        return s + torch.where(keep, self.li.variance, torch.zeros_like(s))

    def constant_map(self, c: int) -> bool:
        """Whether map c is a constant (alpha_y with ``alpha_y="constant"``)."""
        return c == 1 and self.alpha_y == "constant"

    def hyper_labels(self, name: str, shape: torch.Size) -> list[str]:
        """Readable names of a raw parameter's coordinates (``gp.hyper.posterior.hyper_spec``):
        ``lengthscale_{x,y,z}[sin2b|cos2b|sing|cosg]``, ``outputscale_{x,y,z}`` (the maps alpha_x, alpha_y,
        alpha_z) and ``noise_{x,y,z}`` (the force axes F_x, F_y, F_z)."""
        base = {"kernel.base_kernel.raw_lengthscale": "lengthscale", "kernel.raw_outputscale": "outputscale",
                "likelihood.noise_covar.raw_noise": "noise", "li.raw_variance": "li_variance"}.get(name)
        if base is None:
            raise ValueError(f"no label for the 3-D hyperparameter {name!r}")
        if base == "lengthscale":
            dims = ("sin2b", "cos2b", "sing", "cosg")
            return [f"lengthscale_{'xyz'[i // 4]}[{dims[i % 4]}]" for i in range(shape.numel())]
        return [f"{base}_{a}" for a in "xyz"]

    def fixed_labels(self) -> list[str]:
        """Coordinates no likelihood sees: alpha_y's lengthscales when alpha_y is a constant (a hyperparameter
        posterior leaves them where they are), and its Li et al.'s variance."""
        if self.alpha_y != "constant":
            return []
        return self.hyper_labels("kernel.base_kernel.raw_lengthscale", torch.Size([12]))[4:8] + \
            (["li_variance_y"] if self.li is not None else [])

    def as_dict(self) -> dict[str, list | str]:
        ls = self.lengthscale.detach()
        out: dict[str, list | str] = {"lengthscale_x": ls[0, 0].tolist(), "lengthscale_z": ls[2, 0].tolist(),
               "outputscale": self.outputscale.tolist(), "noise": self.noise.tolist(), "alpha_y": self.alpha_y}
        if self.alpha_y == "map":
            out["lengthscale_y"] = ls[1, 0].tolist()
        if self.li is not None:  # a constant alpha_y has no term: its entry (unused) is left out
            v = self.li.variance.tolist()
            out["li_variance"] = [v[0], v[2]] if self.alpha_y == "constant" else v
        return out
