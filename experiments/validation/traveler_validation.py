"""A real leg's log through this package's statics, and alpha_z at beta = 0 from its penetration.

Data: a Traveler leg log (--data DIR, e.g. ../shared/data/traveler_leg; not shipped). Run time:
about 60 s.

    python experiments/validation/traveler_validation.py --data ../shared/data/traveler_leg [--out experiments/results]

1. Statics: ``hardware.traveler`` maps the log's motor angles and torques to this package's
   FiveBarLeg (0.1 / 0.2 m links, 0.05 m extension) and F = -J^-T tau gives the force of the ground
   on the toe; compared with the controller's own ``toeforce_*`` (RMS difference per axis, and the
   sign convention that makes them agree, with the physical checks that fix the sign).
2. alpha_z at beta = 0, moving down (gamma = +pi/2) and up (gamma = -pi/2): the toe is a flat plate
   (the log does not say which toe was fitted; default the I-RFT paper's experimental I-toe, 80 x 8
   mm, ``--toe-length/--toe-width``; alpha_z x area does not depend on it and is reported too),
   the free surface at the protocol's ``ground_height`` below the hip. The force of the leg's own
   dynamics and friction is removed by the same trial's in-air samples moving in the same direction
   (mean over the stroke above the stated surface). Samples: the toe below the stated surface and
   moving faster than ``--min-speed``. Two estimates, each with a 95 % interval:
   - least squares through the origin, F_z = alpha_z x depth x area, with the residuals' integrated
     autocorrelation time inflating the standard error (the 1 kHz samples are not independent);
   - I-RFT (``irft.InverseRFT`` on the plate's contacts along the logged path, thinned to one sample
     per autocorrelation time), its posterior at (0, +pi/2) and (0, -pi/2).
Writes traveler_validation.md and traveler_forces.png to --out. The data are read, never copied.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path as FilePath

import numpy as np
import torch

import irft_torch as irft
from irft_torch.gp.surface.profile import profile_surface
from irft_torch.hardware.traveler import TRAVELER_LEG, read_traveler_log
from irft_torch.metrics import integrated_autocorrelation_time
from irft_torch.rft import IToe, Path, contacts


def smooth(x: np.ndarray, t: np.ndarray, window: float) -> np.ndarray:
    """Centred moving average over a time window [s] (zero phase)."""
    out = np.empty_like(x)
    lo = np.searchsorted(t, t - window / 2)
    hi = np.searchsorted(t, t + window / 2, side="right")
    c = np.concatenate([[0.0], np.cumsum(x)])
    out[:] = (c[hi] - c[lo]) / (hi - lo)
    return out


def window_velocity(y: np.ndarray, t: np.ndarray, window: float) -> np.ndarray:
    """Centred difference over a time window [s]: (y(t + w/2) - y(t - w/2)) / elapsed time."""
    lo = np.searchsorted(t, t - window / 2)
    hi = np.clip(np.searchsorted(t, t + window / 2, side="right") - 1, 0, len(t) - 1)
    return (y[hi] - y[lo]) / np.maximum(t[hi] - t[lo], 1e-9)


def ls_free_surface(d_cm: np.ndarray, f: np.ndarray, area: float, lo: float = -3.0, hi: float = 2.0,
                    step: float = 0.01) -> dict:
    """F = alpha x area x relu(depth + offset), least squares, the offset (cm) profiled on a grid.

    Its 95 % interval: offsets where the residual sum of squares exceeds the minimum by at most
    3.84 x the residual variance x the residuals' autocorrelation time (correlated samples). Returns
    offset, lo, hi, alpha, se (alpha's standard error at the best offset, inflated likewise), tau.
    """
    grid = np.arange(lo, hi + step / 2, step)
    sse, slopes = [], []
    for g in grid:
        w = np.clip(d_cm + g, 0, None) * area
        ww = float((w * w).sum())
        a = float((w * f).sum() / ww) if ww > 0 else 0.0
        slopes.append(a)
        sse.append(float(((f - a * w) ** 2).sum()))
    sse = np.asarray(sse)
    i = int(np.argmin(sse))
    w = np.clip(d_cm + grid[i], 0, None) * area
    r = f - slopes[i] * w
    tau = max(1.0, integrated_autocorrelation_time(r))
    var = float(sse[i]) / max(len(f) - 2, 1)
    inside = grid[sse - sse[i] <= 3.84 * var * tau]
    se = math.sqrt(var * tau / max(float((w * w).sum()), 1e-300))
    return dict(offset=float(grid[i]), lo=float(inside.min()), hi=float(inside.max()), alpha=slopes[i], se=se, tau=tau)


def ls_through_origin(w: np.ndarray, f: np.ndarray) -> tuple[float, float, float]:
    """Slope, its standard error inflated by the residuals' integrated autocorrelation time, and tau."""
    a = float((w * f).sum() / (w * w).sum())
    r = f - a * w
    tau = max(1.0, integrated_autocorrelation_time(r))
    se = math.sqrt(r.var(ddof=1) * tau / (w * w).sum())
    return a, se, tau


class _HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """--help prints the whole module docstring as written, and every option's default."""


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="traveler_validation.py", description=__doc__, formatter_class=_HelpFormatter)
    ap.add_argument("--data", type=FilePath, required=True, default=argparse.SUPPRESS,
                    help="directory with the Traveler log (read, never copied)")
    ap.add_argument("--file", default="traveler_trial_2024-02-02.csv", help="the log's file name in --data")
    ap.add_argument("--out", type=FilePath, default="experiments/results", help="where the report and figure go")
    ap.add_argument("--li-basis", action="store_true",
                    help="the I-RFT fits with Li et al.'s basis as a kernel term (MapPrior(kernel='li'))")
    ap.add_argument("--generic-shape", action="store_true",
                    help="the I-RFT fits with the generic shape's uncertain scale too (MapPrior(kernel="
                         "'li+generic'))")
    ap.add_argument("--toe-length", type=float, default=0.08, help="flat toe length, m (assumed; not in the log)")
    ap.add_argument("--toe-width", type=float, default=0.008, help="flat toe width, m (assumed; not in the log)")
    ap.add_argument("--min-speed", type=float, default=0.02, help="m/s: slower samples are not 'moving'")
    ap.add_argument("--smooth", type=float, default=0.02, help="s: moving-average window for positions and forces")
    ap.add_argument("--velocity-window", type=float, default=0.05, help="s: window of the centred velocity difference")
    ap.add_argument("--n-iter", type=int, default=1000,
                    help="Adam steps of the I-RFT fits (300 leave the hyperparameters unconverged on this log)")
    ap.add_argument("--surface-band", type=float, default=2.0,
                    help="cm: samples from this far above the stated surface down enter the free-surface fits")
    args = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")  # this script only writes files; set here, never at import
    import matplotlib.pyplot as plt

    torch.set_default_dtype(torch.float64)
    path = args.data / args.file
    if not path.is_file():
        raise SystemExit(f"no Traveler log at {path} (the data are not shipped)")
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    log = read_traveler_log(path)
    t = log.time
    lines = ["# Traveler leg: statics and alpha_z at beta = 0 from a real log", "",
             f"Command: `python experiments/validation/traveler_validation.py --data DIR` "
             f"(file {args.file}, {len(log)} samples "
             f"over {t[-1] - t[0]:.2f} s; data by others, read from DIR, not copied).", ""]

    # ---- 1. statics -----------------------------------------------------------------------
    F, valid = log.ground_force(TRAVELER_LEG)
    ctrl = log.controller_force()
    pos_err = (TRAVELER_LEG.forward_kinematics(log.joint_angles()) - log.toe_position()).abs().max().item()
    rms = lambda d: d.pow(2).mean(0).sqrt().tolist()  # noqa: E731
    combos = {"(F_x, F_z)": F, "(-F_x, -F_z)": -F, "(-F_x, F_z)": F * torch.tensor([-1.0, 1.0]),
              "(F_x, -F_z)": F * torch.tensor([1.0, -1.0])}
    lines += ["## 1. Statics: F = -J^-T tau against the controller's toeforce", "",
              "Mapping (``irft_torch.hardware.traveler``): q = (pi - position, pi - position1), "
              "tau = (-torque, torque1), "
              "``TRAVELER_LEG = FiveBarLeg(0.1, 0.2, extension=0.05)``; F is the force of the ground on the toe, x as "
              f"``toe_position_x``, z up. Forward kinematics reproduce the logged toe position to "
              f"{1e3 * pos_err:.1e} mm; "
              f"all {int(valid.sum())} samples are far from singular (condition number "
              f"{TRAVELER_LEG.condition_number(log.joint_angles()).max().item():.2f} at most).", "",
              "| toeforce compared with | RMS difference x [N] | RMS difference z [N] |", "|---|---|---|"]
    for name, v in combos.items():
        rx, rz = rms(v - ctrl)
        lines.append(f"| {name} | {rx:.2e} | {rz:.2e} |")
    z = log.toe_position()[:, 1].numpy()
    rest_air = (t > 1.0) & (t < 2.5)
    hold = (z < -0.259) & (t > 4.0) & (t < 5.5)
    lines += ["", f"So toeforce = (F_x, -F_z): its vertical axis is the force of the toe on the ground, its horizontal "
              f"axis that of the ground on the toe (the controller's own statics give F; it logs the vertical "
              f"component negated). The "
              f"sign of F is fixed by physics, not by the controller: at rest in air F_z = "
              f"{F[rest_air, 1].mean().item():+.2f} N (the links' weight pulls the toe down), held 3.7 cm below the "
              f"stated surface F_z = {F[hold, 1].mean().item():+.2f} N (the sand pushes up).", ""]

    # ---- 2. alpha_z at beta = 0 -------------------------------------------------------------
    ground = log.ground_height
    zs = smooth(z, t, args.smooth)
    xs = smooth(log.toe_position()[:, 0].numpy(), t, args.smooth)
    vz = window_velocity(zs, t, args.velocity_window)
    Fz = smooth(F[:, 1].numpy(), t, args.smooth)
    Fx = smooth(F[:, 0].numpy(), t, args.smooth)
    flag = log["state flag"]
    signed = -(zs + ground)  # depth below the stated surface, m (negative above it)
    depth = np.clip(signed, 0, None)
    A_cm2 = args.toe_length * args.toe_width * 1e4
    band = args.surface_band / 100
    out = {}
    for name, sign, state in (("down", -1, 1.0), ("up", +1, 2.0)):
        moving = (flag == state) & (sign * vz > args.min_speed)
        air = moving & (zs > -ground)
        sand = moving & (zs < -ground)
        near = moving & (signed > -band)  # in sand, or in air within --surface-band above the stated surface
        base = np.array([Fx[air].mean(), Fz[air].mean()])
        w = depth[sand] * 100 * A_cm2  # cm^3
        f = Fz[sand] - base[1]
        a, se, tau = ls_through_origin(w, f)
        # the stroke's direction: a straight line x(z) through its samples in sand (the 1 kHz position
        # signal is too noisy to differentiate sample by sample; the protocol commands a vertical stroke)
        dxdz = float(np.polyfit(zs[sand], xs[sand], 1)[0])
        hinge = ls_free_surface(100 * signed[near], Fz[near] - base[1], A_cm2)
        out[name] = dict(n_air=int(air.sum()), n_sand=int(sand.sum()), n_near=int(near.sum()), base=base, alpha=a,
                         se=se, tau=tau, kA=a * A_cm2, max_depth=float(depth[sand].max()), mask=sand, near=near, f=f,
                         w=w, dxdz=dxdz, hinge=hinge)
    # I-RFT on both strokes: a flat plate along the logged (smoothed) path, thinned by the autocorrelation time
    # of the residuals of the free-surface least squares (the model being fitted; the through-origin line's
    # residuals are long runs of misfit, not noise)
    stride = int(math.ceil(max(out["down"]["hinge"]["tau"], out["up"]["hinge"]["tau"])))
    idx = np.nonzero(out["down"]["near"] | out["up"]["near"])[0][::stride]
    toe = IToe(args.toe_length, args.toe_width, n_segments=1)
    vx = np.zeros_like(vz)
    for o in out.values():
        vx[o["near"]] = o["dxdz"] * vz[o["near"]]
    zeros = torch.zeros(len(t))
    path = Path(torch.as_tensor(t), torch.as_tensor(np.stack([xs, zs + ground], -1)), zeros,
                torch.as_tensor(np.stack([vx, vz], -1)), zeros.clone())
    c = contacts(toe, path)[torch.as_tensor(idx)]  # signed depths kept: the surface can move
    down_rows = vz[idx] < 0
    base = np.where(down_rows[:, None], out["down"]["base"], out["up"]["base"])
    fobs = torch.as_tensor(np.stack([Fx[idx], Fz[idx]], -1) - base)
    angles = (torch.tensor([0.0, 0.0]), torch.tensor([math.pi / 2, -math.pi / 2]))
    fits = {}
    kernel = "li+generic" if args.generic_shape else ("li" if args.li_basis else "rbf")
    for key, kw in (("stated", {}), ("free", {"surface": True}),
                    ("per stroke", {"surface": torch.as_tensor(np.where(down_rows, 0, 1))})):
        torch.manual_seed(0)
        m = irft.InverseRFT(c, fobs, prior=irft.MapPrior(kernel=kernel), **kw)
        if kw:  # the likelihood in the offset has local optima: start at the best of a coarse grid
            m.init_surface(torch.arange(-3.5, 2.0001, 0.1) / 100)  # m
        m.fit(n_iter=args.n_iter, lr=0.05, progress=False)
        fits[key] = (m, m.stress_map(*angles), m.surface_offset.in_cm() if kw else None)  # reported in cm
    g = c.gamma[c.area_z > 0]
    lines += ["## 2. alpha_z at beta = 0 (flat toe), moving down and up, with the free surface learned", "",
              f"Stated free surface: the protocol's ground_height, {100 * ground:.1f} cm below the hip; assumed toe "
              f"{1000 * args.toe_length:.0f} x {1000 * args.toe_width:.0f} mm (area {A_cm2:.2f} cm^2; "
              "the log does not say "
              f"which toe was fitted). In-air force removed per direction (mean while moving the same way above the "
              f"stated surface): down {out['down']['base'][1]:+.2f} N, up {out['up']['base'][1]:+.2f} N (z). "
              f"Samples moving faster than {100 * args.min_speed:.0f} cm/s below the stated surface: down "
              f"{out['down']['n_sand']}, up {out['up']['n_sand']} (max depth {100 * out['down']['max_depth']:.1f} cm); "
              f"with those up to {args.surface_band:.0f} cm above it (so that the surface may also move up): down "
              f"{out['down']['n_near']}, up {out['up']['n_near']}. Their gamma spans "
              f"{g.min().item():+.2f} .. {g.max().item():+.2f} rad "
              f"(each stroke's direction from a line x(z): dx/dz = {out['down']['dxdz']:+.3f} down, "
              f"{out['up']['dxdz']:+.3f} up).", "",
              "The surface offset is in cm, positive when the sand surface is higher than stated (docs/surface.md); "
              "intervals are 95 %.", "",
              "| direction | least squares, stated surface: alpha_z [N/cm^3] | least squares, free "
              "surface: offset [cm], "
              "alpha_z [N/cm^3] | I-RFT, stated surface: alpha_z [N/cm^3] | I-RFT, free surface (one offset): "
              "alpha_z [N/cm^3] | I-RFT, one offset per stroke: alpha_z [N/cm^3] |",
              "|---|---|---|---|---|---|"]

    def gp_cell(key, k):
        post = fits[key][1]
        m, sd = post.mean[k, 1].item(), post.stddev[k, 1].item()
        return f"{m:.4f} ({m - 1.96 * sd:.4f} .. {m + 1.96 * sd:.4f})"

    for k, (name, gam) in enumerate((("down", "+pi/2"), ("up", "-pi/2"))):
        o, h = out[name], out[name]["hinge"]
        lines.append(f"| {name} (gamma {gam}) | {o['alpha']:.4f} ({o['alpha'] - 1.96 * o['se']:.4f} .. "
                     f"{o['alpha'] + 1.96 * o['se']:.4f}) | {h['offset']:+.2f} ({h['lo']:+.2f} .. {h['hi']:+.2f}); "
                     f"{h['alpha']:.4f} ({h['alpha'] - 1.96 * h['se']:.4f} .. {h['alpha'] + 1.96 * h['se']:.4f}) | "
                     f"{gp_cell('stated', k)} | {gp_cell('free', k)} | {gp_cell('per stroke', k)} |")
    est, est2 = fits["free"][2], fits["per stroke"][2]

    def off_cell(e, i):
        lo, hi = e.interval(0.95)
        return (f"{e.mean[i].item():+.3f} +- {e.std[i].item():.3f} cm (95 %: {lo[i].item():+.3f} .. "
                f"{hi[i].item():+.3f}; {e.std_conditional[i].item():.3f} with the hyperparameters fixed)")

    corr = est.correlation.get("kernel.raw_outputscale[1]", [math.nan])[0]
    # profile likelihoods: independent of the Laplace approximation and of where Adam stopped
    def profiled(cc, ff, centre, half):
        grid = centre + torch.arange(-half, half + 1e-4, 0.1)  # cm
        p = profile_surface(cc, ff, grid / 100, n_iter=args.n_iter, lr=0.05)  # offsets in m
        p = {**p, "offsets": p["offsets"] * 100, "best": p["best"] * 100,
             "interval": tuple(v * 100 for v in p["interval"])}  # back to cm for the report
        lo, hi = p["interval"]
        edge = " (a grid end: at least that far)" if lo <= grid[0] + 1e-9 or hi >= grid[-1] - 1e-9 else ""
        return p, f"best {p['best']:+.2f} cm, 95 % interval {lo:+.2f} .. {hi:+.2f} cm{edge}"

    sel = torch.as_tensor(down_rows)
    prof_down, prof_down_txt = profiled(c[sel], fobs[sel], est2.mean[0].item(), 1.5)
    prof_one, prof_one_txt = profiled(c, fobs, est.mean.item(), 1.0)
    laplace_ok = prof_down["interval"][1] - prof_down["interval"][0] < 2 * 1.96 * 1.5 * est2.std[0].item()
    stuck = not (prof_one["interval"][0] - 1e-9 <= est.mean.item() <= prof_one["interval"][1] + 1e-9)
    h_down = out["down"]["hinge"]
    lines += ["", f"**Learned surface, one offset per stroke (the estimate this log supports):** down "
              f"{off_cell(est2, 0)}; "
              f"up {off_cell(est2, 1)}. Profile likelihood of the down stroke's offset (its samples alone, the offset "
              f"fixed on a 0.1 cm grid over +-1.5 cm, hyperparameters refitted): {prof_down_txt}"
              + ("" if laplace_ok else ": much wider than the Laplace interval, the likelihood is not quadratic "
                 "over it (two onsets fit the stroke: a weak rise near -1.7 cm and the steep one near -2.7 cm; the "
                 "Laplace std sees only the curvature at the mode it sits in); the profile interval is the one to "
                 "quote")
              + f". The least squares with a free surface on the down stroke agrees: {h_down['offset']:+.2f} cm "
              f"({h_down['lo']:+.2f} .. {h_down['hi']:+.2f}).", "",
              f"One offset for the whole recording: {off_cell(est, 0)}; its correlation with the z map's log "
              f"outputscale {corr:+.2f}. Its profile likelihood: {prof_one_txt}"
              + ("; the joint fit's offset lies outside it: Adam stopped at a local optimum of a likelihood with two "
                 "modes (the down stroke's and the up stroke's), where the Laplace std describes only the local "
                 "curvature. One surface for both strokes does not describe this log." if stuck else "."), "",
              f"Least squares with a free surface (per stroke, F_z = alpha_z x area x relu(depth + offset), the "
              "offset profiled on a 0.01 cm grid over -3 .. +2 cm, its interval where the residual sum "
              "of squares rises "
              "by 3.84 residual variances x the autocorrelation time): autocorrelation time of its residuals "
              f"{out['down']['hinge']['tau']:.0f} (down), {out['up']['hinge']['tau']:.0f} (up) samples, against "
              f"{out['down']['tau']:.0f} and {out['up']['tau']:.0f} for the line through the origin at the stated "
              "surface.", "",
              f"I-RFT: {len(idx)} samples (every {stride}th moving sample from {args.surface_band:.0f} cm above the "
              f"stated surface down, both strokes), zero prior mean, the offsets started at the best of a 0.1 cm grid "
              f"over -3.5 .. +2 cm (``init_surface``; from 0, Adam stops on the shoulder near -1.7 cm, a local "
              f"optimum), {args.n_iter} Adam steps (lr 0.05); "
              f"hyperparameters with one offset per stroke {fits['per stroke'][0].hyperparameters()}.", ""]
    ratio = fits["per stroke"][1].mean[0, 1].item() / max(fits["stated"][1].mean[0, 1].item(), 1e-12)
    lo_d, hi_d = prof_down["interval"]
    # alpha_z moving down at the two ends of the offset's profile interval (the offset fixed, both strokes)
    ends = []
    for d_end in (hi_d, lo_d):
        m_end = irft.InverseRFT(c.with_surface_offset(d_end / 100), fobs)
        m_end.fit(n_iter=args.n_iter, lr=0.05, progress=False)
        p_end = m_end.stress_map(*angles)
        ends.append((d_end, p_end.mean[0, 1].item(), p_end.stddev[0, 1].item()))
    lines += ["alpha_z moving down with the offset fixed at the ends of its profile interval: "
              + "; ".join(f"{d:+.2f} cm: {a:.4f} ({a - 1.96 * sd:.4f} .. {a + 1.96 * sd:.4f}) N/cm^3"
                          for d, a, sd in ends)
              + ". The I-RFT intervals in the table hold the offset at its fitted value: the surface's "
              "uncertainty is the larger part of alpha_z's here.", ""]
    lines += [f"Reading: moving down, the force stays near the in-air level until the toe is {-hi_d:.1f} to "
              f"{-lo_d:.1f} cm below the stated surface (profile 95 %): the sand's effective surface lies that much "
              f"lower than the protocol's ground_height, and alpha_z moving down (with the per-stroke offset "
              f"{est2.mean[0].item():+.2f} cm) is {ratio:.1f} times the estimate "
              "at the stated surface (which spreads the same force over depths where there was none). Moving up, "
              "the plate meets almost no resistance: the up stroke's force is a short transient at the bottom of the "
              "stroke, which the free-surface model can only read as a 'surface' just above the deepest point (its "
              "offset and its alpha_z depend on that reading; at the stated surface alpha_z up is near 0). Its "
              "offset is not the sand's surface.", ""]

    fig, axes = plt.subplots(1, 3, figsize=(14, 4))
    ax = axes[0]
    ax.plot(t, ctrl[:, 1].numpy(), color="0.6", lw=2, label="controller toeforce_y")
    ax.plot(t, F[:, 1].numpy(), "tab:blue", lw=0.7, label="package F_z = -J^-T tau")
    ax.plot(t, -F[:, 1].numpy(), "tab:orange", lw=0.7, ls="--", label="-F_z")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("force [N]")
    ax.legend(fontsize=7)
    ax.set_title("statics: controller vs package")
    ax2 = ax.twinx()
    ax2.plot(t, 100 * z, "k:", lw=0.8)
    ax2.axhline(-100 * ground, color="tab:brown", lw=0.8)
    ax2.axhline(-100 * ground + est2.mean[0].item(), color="tab:green", lw=0.8, ls="--")
    ax2.set_ylabel("toe z [cm]: path (dotted),\nsurface stated (brown) / learned (green)", fontsize=8)
    post = fits["per stroke"][1]
    for k, (ax, name) in enumerate(zip(axes[1:], ("down", "up"))):
        delta = est2.mean[k].item()
        o = out[name]
        d = 100 * signed[o["near"]]
        ax.plot(d, Fz[o["near"]] - o["base"][1], ".", ms=2, alpha=0.4, color="0.5", label="samples "
                        "(in-air level removed)")
        dd = np.linspace(d.min(), d.max(), 200)
        ax.plot(dd, o["alpha"] * A_cm2 * np.clip(dd, 0, None), "r-",
                label=f"LS, stated surface: alpha_z = {o['alpha']:.3f} N/cm^3")
        m_a, sd_a = post.mean[k, 1].item(), post.stddev[k, 1].item()
        h = np.clip(dd + delta, 0, None) * A_cm2
        ax.plot(dd, m_a * h, "g-", label=f"I-RFT, learned surface (per stroke): alpha_z = {m_a:.3f} N/cm^3")
        ax.fill_between(dd, (m_a - 1.96 * sd_a) * h, (m_a + 1.96 * sd_a) * h, color="g", alpha=0.2)
        ax.axvline(0, color="tab:brown", lw=0.8, label="stated surface")
        lo, hi = est2.interval(0.95)
        ax.axvspan(-hi[k].item(), -lo[k].item(), color="tab:green", alpha=0.15, lw=0)
        ax.axvline(-delta, color="tab:green", lw=0.8, ls="--", label=f"learned surface ({delta:+.2f} cm, 95 % band)")
        ax.set_xlabel("depth below the stated surface [cm]")
        ax.set_ylabel("F_z [N]")
        ax.set_title(f"moving {name}")
        ax.legend(fontsize=6.5, loc="upper left")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(args.out / "traveler_forces.png", dpi=120)
    plt.close(fig)
    lines.append(f"({time.perf_counter() - t0:.0f} s.) Figure: traveler_forces.png (right panels: the per-stroke "
                 "learned surface, its Laplace 95 % band shaded).")
    text = "\n".join(lines) + "\n"
    (args.out / "traveler_validation.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
