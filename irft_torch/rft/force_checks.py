"""Do measured forces look like a granular medium's at the stated contacts? Units, signs, columns.

Every granular medium measured so far has stress maps close to the generic map of Li, Zhang &
Goldman (2013) times a scale zeta of order 1 (0.25 for loose poppy seeds; DEM plates correlate
0.95 with it): the medium lifts a toe that moves into it (F_z > 0) and drags against the motion.
So the forces of the generic map on the stated contacts, g = ``forces(generic, contacts)``, are a
yardstick for measured forces F, per axis a (over the samples in contact):

    scale_a = rms(F_a) / rms(g_a)         (a medium's zeta: 1e3 off when F is in mN or kN, or the
                                           weights in mm^3 or m^3; far off when the stated depth is)
    cos_a   = sum F_a g_a / (|F_a| |g_a|) (-1 when a sign is flipped: the air run and the trial
                                           swapped, the force on the leg instead of on the toe)

and ``cos`` against the other axis's g says whether F_x and F_z were swapped. ``force_faults``
turns these into plain-language findings; the callers say what to do (``InverseRFT`` warns,
``irft ingest`` refuses).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .contacts import Contacts
from .forces import forces as rft_forces
from .stress_maps import FourierStressMap

__all__ = ["GenericComparison", "ForceFault", "compare_with_generic", "force_faults", "SCALE_RANGE"]

SCALE_RANGE = (0.01, 30.0)  # zeta of any granular medium measured: loose poppy seeds 0.25, DEM plates ~1
_FLIPPED = -0.3  # F_z's cosine below this: the force points against the medium's lift
_SWAPPED = 0.5  # a slip (a sign, swapped columns) that explains the forces at least this well, 0.3 better than as given


@dataclass
class GenericComparison:
    """Measured forces against the generic map's on the same contacts, per axis (x, z): ``scale``
    rms ratio, ``cos`` cosine similarity, ``crossed_cos`` (cos(F_x, g_z), cos(F_z, g_x)), over the
    ``n_contact`` samples in contact; ``outside`` the rms force (2,) N where the stated geometry has
    the toe out of the sand (NaN when there is no such sample) and ``inside`` where it is in."""

    scale: Tensor
    cos: Tensor
    crossed_cos: Tensor
    n_contact: int
    outside: Tensor
    inside: Tensor


def _cos(a: Tensor, b: Tensor) -> Tensor:
    den = a.norm(dim=0) * b.norm(dim=0)
    return torch.where(den > 0, (a * b).sum(0) / den.clamp_min(1e-300), torch.zeros_like(den))


def compare_with_generic(contacts: Contacts, forces) -> GenericComparison:
    """Compare forces (T, 2) N with the generic map's forces on ``contacts`` (T, M) (cm^3 weights).

    Example:
        >>> cmp = compare_with_generic(c, f)
        >>> cmp.scale, cmp.cos        # about (1, 1.5) and (1, 1) for FourierStressMap.generic(1, 1.5)
    """
    if contacts.beta.ndim != 2:
        raise ValueError(f"contacts must be (T, M), got {tuple(contacts.shape)}")
    f = torch.as_tensor(forces).to(torch.float64)
    c = contacts.to(dtype=torch.float64)
    with torch.no_grad():
        g = rft_forces(FourierStressMap.generic().to(torch.float64), c)
    on = ((c.weight_x != 0) | (c.weight_z != 0)).any(-1)
    fi, gi = f[on], g[on]
    rms = lambda x: x.pow(2).mean(0).sqrt() if len(x) else torch.full((2,), float("nan"), dtype=torch.float64)  # noqa: E731
    scale = rms(fi) / rms(gi).clamp_min(1e-300)
    return GenericComparison(scale, _cos(fi, gi), _cos(fi, gi.flip(-1)), int(on.sum()), rms(f[~on]), rms(fi))


@dataclass(frozen=True)
class ForceFault:
    """One finding of ``force_faults``: ``kind`` ("sign", "swapped", "large", "small", "outside"), what
    was measured (``finding``) and the usual causes (``guess``); ``str`` joins the two."""

    kind: str
    finding: str
    guess: str

    def __str__(self) -> str:
        return f"{self.finding}: {self.guess}"


def force_faults(contacts: Contacts, forces, scale_range: tuple[float, float] = SCALE_RANGE) -> list[ForceFault]:
    """What is implausible about forces (T, 2) N on contacts (T, M) for a granular medium: "swapped"
    (F_x and F_z exchanged), "sign" (an axis against the medium's lift or drag), "large" / "small" (a
    scale beyond ``scale_range`` of the generic map's: a unit or a stated depth off), "outside" (forces
    where the stated geometry has the toe out of the sand, as large as those in it). Empty when nothing
    is found or fewer than 3 samples are in contact.

    Examples:
        >>> [str(f) for f in force_faults(c, 1000 * f)]
        ['F_z is 1e+03x what the generic granular medium gives at these depths (...): are the forces in mN, ...']
    """
    cmp = compare_with_generic(contacts, forces)
    out: list[ForceFault] = []
    if cmp.n_contact < 3:
        return out
    cos, crossed, scale = cmp.cos.tolist(), cmp.crossed_cos.tolist(), cmp.scale.tolist()
    # how well the forces match the generic ones as given and under each slip (mean cosine of the two axes)
    z_sign = ("F_z has the wrong sign", "down, where a medium lifts a toe moving into it")
    slips = {
        ("F_x has the wrong sign", "along the motion, where a medium drags against it"): (-cos[0] + cos[1]) / 2,
        z_sign: (cos[0] - cos[1]) / 2,
        ("both axes have the wrong sign", "the force on the leg instead of the force on the toe?"):
            -(cos[0] + cos[1]) / 2,
        ("the force columns look swapped", "(F_z, F_x) given for (F_x, F_z)?"): (crossed[0] + crossed[1]) / 2,
    }
    given = (cos[0] + cos[1]) / 2
    ranked = sorted(slips.items(), key=lambda kv: -kv[1])
    (best, fit), (second, fit2) = ranked[0], ranked[1]
    if (fit > _SWAPPED and fit > given + 0.3) or cos[1] < _FLIPPED:
        if fit <= given + 0.3:  # F_z against the lift, but no one slip explains the forces better
            best, fit = z_sign, slips[z_sign]
        finding = (f"{best[0]} (the forces match the generic map's with a cosine of {fit:.2f} read that way, "
                   f"{given:.2f} as given)")
        guess = best[1] + (f" Or {second[0].replace('the force', 'force')} ({fit2:.2f})"
                           if fit2 > fit - 0.05 and fit2 > given + 0.3 else "")
        out.append(ForceFault("swapped" if "swapped" in best[0] else "sign", finding, guess))
    names = ("F_x", "F_z")
    lo, hi = scale_range
    for a in (1, 0):
        s = scale[a]
        if not s == s:  # NaN: no force scale to compare
            continue
        size = "zero in every sample in contact" if s == 0 else \
            f"{s:.3g}x what the generic granular medium gives at these depths"
        finding = f"{names[a]} is {size} (any medium measured: {lo:g}x to {hi:g}x)"
        if s > hi:
            out.append(ForceFault("large", finding, "are the forces in mN, the weights in m^3, or the toe deeper "
                                                    "than stated?"))
            break
        if s < lo:
            out.append(ForceFault("small", finding, "are the forces in kN, the weights in mm^3, the toe shallower "
                                                    "than stated, or is this a run in air?"))
            break
    outside, inside = cmp.outside.tolist(), cmp.inside.tolist()
    n_out = int((~((contacts.weight_x != 0) | (contacts.weight_z != 0)).any(-1)).sum())
    if n_out >= 3 and outside[1] == outside[1] and outside[1] > 0.5 * inside[1] > 0:
        out.append(ForceFault("outside", f"the force where the stated geometry has the toe out of the sand (rms F_z "
                                         f"{outside[1]:.3g} N) is as large as in it ({inside[1]:.3g} N)",
                              "is the toe deeper than stated, or the force in air not subtracted?"))
    return out
