"""Granular RFT stress-per-depth maps in the Fourier form of Li, Zhang & Goldman (2013).

    alpha_z(b, g) = sum_{m in -1..1, n in 0..1} A_mn cos(2 m b + n g) + B_mn sin(2 m b + n g)
    alpha_x(b, g) = sum_{m in -1..1, n in 0..1} C_mn cos(2 m b + n g) + D_mn sin(2 m b + n g)

``b`` (beta) is the tilt of a surface element from the horizontal, ``g`` (gamma) the direction of
its velocity from the horizontal, positive downward, for motion toward +x (DESIGN.md). The maps
are in N/cm^3: force [N] = alpha x depth [cm] x area [cm^2].
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor, nn

__all__ = ["FourierStressMap", "GENERIC", "POPPY_LOOSE", "POPPY_CLOSE", "mirror_to_canonical"]

# Coefficients keyed by (m, n), from Table S2 of Li et al. 2013 (see shared/reference/rft_facts.md).
# Only the non-zero terms are listed; every other (m, n) coefficient is 0.
GENERIC: dict[str, Any] = {
    "A": {(0, 0): 0.206, (1, 0): 0.169},
    "B": {(1, 1): 0.212, (0, 1): 0.358, (-1, 1): 0.055},
    "C": {(1, 1): -0.124, (0, 1): 0.253, (-1, 1): 0.007},
    "D": {(1, 0): 0.088},
}
POPPY_LOOSE: dict[str, Any] = {
    "A": {(0, 0): 0.051, (1, 0): 0.047},
    "B": {(1, 1): 0.053, (0, 1): 0.083, (-1, 1): 0.020},
    "C": {(1, 1): -0.026, (0, 1): 0.057, (-1, 1): 0.0},
    "D": {(1, 0): 0.025},
}
POPPY_CLOSE: dict[str, Any] = {
    "A": {(0, 0): 0.094, (1, 0): 0.092},
    "B": {(1, 1): 0.092, (0, 1): 0.151, (-1, 1): 0.035},
    "C": {(1, 1): -0.039, (0, 1): 0.086, (-1, 1): 0.018},
    "D": {(1, 0): 0.046},
}

_MS = (-1, 0, 1)
_NS = (0, 1)


def _table(coeffs: dict[tuple[int, int], float]) -> Tensor:
    """(3, 2) float64 table indexed by (m + 1, n)."""
    out = torch.zeros(3, 2, dtype=torch.float64)
    for (m, n), v in coeffs.items():
        if m not in _MS or n not in _NS:
            raise ValueError(f"coefficient index (m={m}, n={n}) outside m in -1..1, n in 0..1")
        if not math.isfinite(float(v)):
            raise ValueError(f"coefficient (m={m}, n={n}) must be finite, got {v}")
        out[m + 1, n] = float(v)
    return out


def wrap_beta(beta: Tensor) -> Tensor:
    """A segment tilt (rad, any shape) wrapped to [-pi/2, pi/2) (period pi); a beta a rounding error
    below -pi/2 is -pi/2, not pi/2 (``torch.remainder`` of -1e-17 rounds to pi)."""
    beta = torch.remainder(beta + math.pi / 2, math.pi) - math.pi / 2
    return torch.where(beta >= math.pi / 2, beta - math.pi, beta)


def mirror_to_canonical(beta: Tensor, gamma: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Map any (beta, gamma) into the canonical square by the mirror identity: beta in [-pi/2, pi/2),
    gamma in [-pi/2, pi/2] (closed: straight down, pi/2, and straight up, -pi/2, are kept).

    Gamma is first wrapped to [-pi, pi) (gamma = pi and -pi are the same direction, straight toward
    -x). For |gamma| > pi/2 (motion with a -x component) returns (-beta, pi - gamma) wrapped, and a
    sign of -1 for the x map: alpha_x(b, g) = -alpha_x(-b, pi - g), alpha_z(b, g) = alpha_z(-b,
    pi - g) (exact identities of the Fourier form). Beta is wrapped to [-pi/2, pi/2) (period pi;
    a beta a rounding error below -pi/2 is -pi/2, not pi/2).

    Returns:
        (beta_c, gamma_c, sign_x), each of the broadcast shape of the inputs.
    """
    beta, gamma = torch.broadcast_tensors(beta, gamma)
    gamma = torch.remainder(gamma + math.pi, 2 * math.pi) - math.pi  # [-pi, pi)
    flip = gamma.abs() > math.pi / 2
    gamma_c = torch.where(flip, torch.remainder(math.pi - gamma + math.pi, 2 * math.pi) - math.pi, gamma)
    beta_c = torch.where(flip, -beta, beta)
    beta_c = wrap_beta(beta_c)
    sign_x = torch.where(flip, -torch.ones_like(gamma), torch.ones_like(gamma))
    return beta_c, gamma_c, sign_x


class FourierStressMap(nn.Module):
    """A stress-per-depth map alpha(beta, gamma) = (alpha_x, alpha_z) in the Li et al. Fourier form.

    Args:
        A: cos coefficients of alpha_z, keyed by (m, n) with m in {-1, 0, 1}, n in {0, 1}, in N/cm^3.
            Missing keys are 0.
        B: sin coefficients of alpha_z, likewise.
        C: cos coefficients of alpha_x, likewise.
        D: sin coefficients of alpha_x, likewise.
        scale_x: multiplies alpha_x (the "zeta" of RFT).
        scale_z: multiplies alpha_z.

    Calling the map broadcasts ``beta`` and ``gamma`` (radians, any shape ``S``) and returns a tensor
    of shape ``S + (2,)``: ``(alpha_x, alpha_z)``. It is differentiable in both angles (and in the
    coefficients, which are buffers that follow ``.to(device)``).

    Example:
        >>> smap = FourierStressMap.generic()
        >>> smap(torch.tensor(0.0, dtype=torch.float64), torch.tensor(math.pi / 2, dtype=torch.float64))[1]
        tensor(1., dtype=torch.float64)
        >>> smap(torch.tensor(0.0), torch.tensor(0.0))   # float32 in, float32 out: a plate dragged toward +x
        tensor([0.1360, 0.3750])
    """

    A: Tensor  # buffers (registered in __init__): Fourier coefficient tables
    B: Tensor
    C: Tensor
    D: Tensor

    def __init__(
        self,
        A: dict[tuple[int, int], float],
        B: dict[tuple[int, int], float],
        C: dict[tuple[int, int], float],
        D: dict[tuple[int, int], float],
        scale_x: float = 1.0,
        scale_z: float = 1.0,
        name: str = "custom",
    ) -> None:
        super().__init__()
        for arg, val in (("scale_x", scale_x), ("scale_z", scale_z)):
            if not math.isfinite(float(val)):
                raise ValueError(f"{arg} must be finite, got {val}")
        self.name = name
        self.register_buffer("A", _table(A) * float(scale_z))
        self.register_buffer("B", _table(B) * float(scale_z))
        self.register_buffer("C", _table(C) * float(scale_x))
        self.register_buffer("D", _table(D) * float(scale_x))

    # ---- presets -------------------------------------------------------------------------
    @classmethod
    def generic(cls, scale_x: float = 1.0, scale_z: float = 1.0) -> FourierStressMap:
        """The generic (dimensionless) Li et al. 2013 shape times per-axis scales (N/cm^3).

        alpha_z(0, pi/2) = scale_z exactly, so ``scale_z`` is the medium's vertical stress per depth
        for a horizontal plate pushed straight down.
        """
        return cls(**GENERIC, scale_x=scale_x, scale_z=scale_z, name="generic")

    @classmethod
    def poppy_seeds_loose(cls) -> FourierStressMap:
        """Loosely packed poppy seeds (Li et al. 2013), N/cm^3."""
        return cls(**POPPY_LOOSE, name="poppy seeds, loosely packed")

    @classmethod
    def poppy_seeds_close(cls) -> FourierStressMap:
        """Closely packed poppy seeds (Li et al. 2013), N/cm^3."""
        return cls(**POPPY_CLOSE, name="poppy seeds, closely packed")

    def scaled(self, scale_x: float = 1.0, scale_z: float = 1.0) -> FourierStressMap:
        """A copy with alpha_x times ``scale_x`` and alpha_z times ``scale_z``."""
        for arg, val in (("scale_x", scale_x), ("scale_z", scale_z)):
            if not math.isfinite(float(val)):
                raise ValueError(f"{arg} must be finite, got {val}")
        new = FourierStressMap({}, {}, {}, {}, name=f"{self.name} (scaled)")
        new.A.copy_(self.A * scale_z)
        new.B.copy_(self.B * scale_z)
        new.C.copy_(self.C * scale_x)
        new.D.copy_(self.D * scale_x)
        return new.to(self.A.device)

    # ---- evaluation ----------------------------------------------------------------------
    def forward(self, beta: Tensor, gamma: Tensor) -> Tensor:
        beta = torch.as_tensor(beta)
        gamma = torch.as_tensor(gamma)
        dtype = torch.promote_types(torch.promote_types(beta.dtype, gamma.dtype), torch.float32)
        if not dtype.is_floating_point:
            dtype = torch.get_default_dtype()
        beta, gamma = torch.broadcast_tensors(beta.to(dtype), gamma.to(dtype))
        coef = self.basis_coefficients().to(dtype=dtype, device=beta.device)
        c2, s2 = torch.cos(2 * beta), torch.sin(2 * beta)
        cg, sg = torch.cos(gamma), torch.sin(gamma)
        # Products shared by both maps; sums of scalar x tensor avoid materializing the basis.
        terms = (c2, s2, cg, sg, c2 * cg, s2 * sg, s2 * cg, c2 * sg)
        out = []
        for axis in range(2):
            k = coef[:, axis]
            acc = terms[0] * k[1] + k[0]
            for i in range(1, 8):
                acc = acc.addcmul_(terms[i], k[i + 1])
            out.append(acc)
        return torch.stack(out, dim=-1)

    @staticmethod
    def basis(beta: Tensor, gamma: Tensor) -> Tensor:
        """The nine functions every (m, n) term is a combination of, shape S + (9,):

        1, cos 2b, sin 2b, cos g, sin g, cos 2b cos g, sin 2b sin g, sin 2b cos g, cos 2b sin g.
        Angle addition turns the six phases 2mb + ng into these, from four transcendental
        evaluations per point.
        """
        c2, s2 = torch.cos(2 * beta), torch.sin(2 * beta)
        cg, sg = torch.cos(gamma), torch.sin(gamma)
        one = torch.ones_like(c2)
        return torch.stack([one, c2, s2, cg, sg, c2 * cg, s2 * sg, s2 * cg, c2 * sg], dim=-1)

    def basis_coefficients(self) -> Tensor:
        """(9, 2) matrix mapping ``basis`` to (alpha_x, alpha_z); differentiable in the tables."""

        def column(cos_t: Tensor, sin_t: Tensor) -> Tensor:
            # cos_t[m + 1, n] multiplies cos(2mb + ng), sin_t[m + 1, n] multiplies sin(2mb + ng)
            return torch.stack([
                cos_t[1, 0],
                cos_t[2, 0] + cos_t[0, 0],
                sin_t[2, 0] - sin_t[0, 0],
                cos_t[1, 1],
                sin_t[1, 1],
                cos_t[2, 1] + cos_t[0, 1],
                -cos_t[2, 1] + cos_t[0, 1],
                sin_t[2, 1] - sin_t[0, 1],
                sin_t[2, 1] + sin_t[0, 1],
            ])

        return torch.stack([column(self.C, self.D), column(self.A, self.B)], dim=-1)

    def extra_repr(self) -> str:
        return f"name={self.name!r}"
