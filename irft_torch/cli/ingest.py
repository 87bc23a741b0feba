"""``irft ingest``: motor logs of repeated trials (and in-air runs along the same path) -> forces ->
air subtraction, zero-phase filter, trial average -> a dataset (contacts and forces), with the
physics checked first and a summary printed."""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import TYPE_CHECKING

from .arguments import UsageError, _out_file, add_protocol_args, add_toe_args, make_toe, warn

if TYPE_CHECKING:
    from ..hardware.bus.log_data import ResampledLog
    from ..hardware.pipeline import ForceTrace


def add_leg_args(p) -> None:
    g = p.add_argument_group("leg and motors (SI units)")
    g.add_argument("--l1", type=float, default=0.15, help="proximal link, m (default 0.15)")
    g.add_argument("--l2", type=float, default=0.30, help="distal link, m (default 0.30)")
    g.add_argument("--hip-spacing", type=float, default=0.0, help="distance between motor axes, m")
    g.add_argument("--extension", type=float, default=0.0,
                   help="how far the toe sits beyond the distal joint along the leg axis, m (Traveler: 0.05)")
    g.add_argument("--hip-height", type=float, default=0.25, help="motor axes above the sand surface, m (positive)")
    g.add_argument("--max-condition", type=float, default=50.0, help="mask samples with cond(J) above this")
    g.add_argument("--kt", type=float, default=None,
                   help="torque constant, N m/A (default: from --kv if given, else the U8-II's 0.0973)")
    g.add_argument("--kv", type=float, help="motor KV (rpm/V), instead of --kt")
    g.add_argument("--kt-convention", choices=["odrive", "si"], default="odrive",
                   help="k_t from --kv: ODrive's 8.27/KV (default) or SI 60/(2 pi KV)")
    g.add_argument("--directions", type=int, nargs=2, default=[1, 1], help="motor direction signs (+1/-1)")
    g.add_argument("--zero-offsets", type=float, nargs=2, default=[0.0, 0.0], help="joint angle at encoder 0, rad")
    g.add_argument("--gear-ratio", type=float, default=1.0,
                   help="motor turns per joint turn (1: direct drive; 1 for MIT mode, which reports the output)")


def _leg_and_motors(a):
    """The leg and both motors from the leg options. k_t: --kt, else from --kv and --kt-convention,
    else the paper's U8-II 0.0973 N m/A."""
    from ..hardware import FiveBarLeg, MotorModel, kt_from_kv

    try:
        leg = FiveBarLeg(a.l1, a.l2, hip_spacing=a.hip_spacing, max_condition=a.max_condition,
                         extension=getattr(a, "extension", 0.0))
    except ValueError as e:
        raise UsageError("--extension" if "extension" in str(e) else "--l1/--l2", str(e)) from None
    if a.kt is not None:
        kt = a.kt
    elif a.kv is not None:
        kt = kt_from_kv(a.kv, a.kt_convention)
    else:
        kt = 0.0973
    try:
        motors = tuple(MotorModel(kt, direction=d, gear_ratio=a.gear_ratio, zero_offset=z)
                       for d, z in zip(a.directions, a.zero_offsets))
    except ValueError as e:
        raise UsageError("--kt/--kv" if "torque_constant" in str(e) else "--gear-ratio", str(e)) from None
    return leg, motors


def _heading(text: str):
    if text in ("link1", "link2"):
        return text
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a toe heading in rad or 'link1'/'link2', got {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"must be finite, got {text!r}")
    return v


def _name_trials(message: str, paths, word: str) -> str:
    """'trial 1 covers ...' -> '<word> 1 (path) covers ...'."""
    import re

    return re.sub(r"\btrial (\d+)\b", lambda m: f"{word} {m[1]} ({paths[int(m[1])]})", message)


def _medium_hint(kind: str, a) -> str:
    """What to check in ``irft ingest``'s options for a finding of ``rft.force_checks.force_faults``."""
    if kind == "sign":
        return ("were the trial and the air run swapped? (the logs in sand come first, the runs in air after --air)"
                if a.air else "check --directions and the sign of --kt (the force of the sand on the toe: F_z > 0 "
                              "while it moves in)")
    if kind == "swapped":
        return "check --nodes (motor 1, motor 2) and --directions"
    if kind == "large":
        return "check --kt/--kv, --hip-height (the toe deeper than stated?) and the toe (--width, --length/--radius, m)"
    if kind == "small":
        return ("is a log in air given as a trial? (the runs in air go after --air) Else check --kt/--kv, --hip-height "
                "and the toe (--width, --length/--radius, m)")
    return ("give the run in air with --air" if not a.air
            else "check --hip-height (the toe deeper than stated?)")


def _leg_hint(message: str, log, leg, motors, a) -> str:
    """``message`` with, where a wrong node order, direction or gear ratio explains the log, the options
    that do (``hardware.leg_options``)."""
    from ..hardware.leg_options import suggest_leg_options

    if log is None:
        return message
    hint = suggest_leg_options(log.position, leg, motors, tuple(a.nodes), a.hip_height, a.max_depth)
    return f"{message}. {hint}" if hint else message


def cmd_ingest(a) -> int:
    import warnings

    from ..hardware import (
        MitModel,
        average_trials,
        build_dataset,
        dataset_summary,
        forces_from_log,
        mit_model,
        read_log,
        save_dataset,
        subtract_air,
        zero_phase_filter,
    )
    from ..rft.force_checks import force_faults

    out = _out_file(a.out, "--out", ".npz")
    for p in [*a.logs, *a.air]:
        if not Path(p).is_file():
            raise UsageError("logs" if p in a.logs else "--air", f"no log file at {p}")
    leg, motors = _leg_and_motors(a)
    toe = make_toe(a)
    if a.protocol == "mit":
        try:
            model = mit_model(a.mit_model)
        except ValueError as e:
            raise UsageError("--mit-model", str(e)) from None
        if a.mit_p_max or a.mit_v_max or a.mit_t_max or a.mit_quantity:
            model = MitModel(model.name + " (custom)", a.mit_p_max or model.p_max, a.mit_v_max or model.v_max,
                             a.mit_t_max or model.t_max, a.mit_quantity or model.quantity)
    else:
        model = None
    read_kw = ({"protocol": "mit", "mit_model": model, "master_id": a.mit_master_id} if model
               else {"firmware": a.firmware})
    first_log: list[ResampledLog] = []  # the first run's resampled log: what the leg-option hints are worked out on

    def runs(path) -> list[tuple[str, ForceTrace]]:
        """(name, ForceTrace) of every recording in the log at ``path`` (a log whose clock restarts
        holds several: each is a run of its own)."""
        data = read_log(path, nodes=set(a.nodes), on_error=a.on_error, channel=a.channel, **read_kw)
        for issue in data.issues:
            print(f"{path}: {issue}")
        recordings = data.recordings()
        out_ = []
        for k, rec in enumerate(recordings):
            name = str(path) if len(recordings) == 1 else f"{path} (recording {k + 1} of {len(recordings)})"
            log = None
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                try:
                    log = rec.resample(tuple(a.nodes), rate=a.rate, max_current=a.max_current,
                                       max_torque=a.max_torque)
                    if not first_log:
                        first_log.append(log)
                    t = forces_from_log(log, leg, motors, arc_noise=a.arc_noise)
                except ValueError as e:
                    msg = f"{name}: {e}"
                    raise ValueError(_leg_hint(msg, log, leg, motors, a) if "reachable" in msg else msg) from None
            for w in caught:
                if "singular" not in str(w.message):
                    warn("ingest", f"{name}: {w.message}")
            for reason in log.masked:
                if " stops " in reason or " starts " in reason:  # a series cut short: the run is cropped, say so
                    warn("ingest", f"{name}: {reason}")
            if t.why_masked:
                print(f"{name}: masked " + "; ".join(f"{v} {k_}" for k_, v in t.why_masked.items()))
            n_valid = int(t.valid.sum())
            if a.filter_window > max(5, n_valid // 10):
                dur = float(t.time[-1] - t.time[0]) if len(t.time) > 1 else 0.0
                share = 100 * a.filter_window / max(n_valid, 1)
                raise UsageError("--filter-window", f"{a.filter_window} samples is {share:.0f} % of {name} ({n_valid} "
                                                    f"samples, {dur:.3g} s): a moving average that long flattens the "
                                                    "force; use a few samples (default 5, at most "
                                                    f"{max(5, n_valid // 10)} here)")
            out_.append((name, t))
        return out_

    def average(traces, paths, word: str, label: str = ""):
        """``average_trials`` of the runs (cropped with --crop-trials), its warnings printed, its errors
        naming the runs' files."""
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                out = average_trials(traces, coverage="crop" if a.crop_trials else "error", path_tol=a.path_tol)
        except ValueError as e:
            raise ValueError(_name_trials(str(e), paths, word)) from None
        for w in caught:
            warn("ingest", f"{label}{w.message}")
        return out

    air_runs = [r for p in a.air for r in runs(p)]
    air = average([t for _, t in air_runs], [n for n, _ in air_runs], "air run", "air runs: ") if air_runs else None
    trial_runs = [r for p in a.logs for r in runs(p)]
    trials = []
    for name, t in trial_runs:
        if air is not None:
            try:
                t = subtract_air(t, air, path_tol=a.path_tol)
            except ValueError as e:
                raise ValueError(f"{name}: {e}") from None
        trials.append(zero_phase_filter(t, a.filter_window))
    names = [n for n, _ in trial_runs]
    avg = average(trials, names, "trial")
    try:
        ds = build_dataset(avg, leg, toe, a.hip_height, heading=a.heading, max_depth=a.max_depth)
    except ValueError as e:
        raise ValueError(_leg_hint(str(e), first_log[0] if first_log else None, leg, motors, a)) from None
    if not a.any_medium:
        faults = force_faults(ds.contacts, ds.forces)
        if faults:
            raise ValueError(f"the forces do not look like a granular medium's at the stated contacts: "
                             f"{faults[0].finding}: {_medium_hint(faults[0].kind, a)} (--any-medium skips this check)")
    if a.statistics:
        from ..gp.statistics import recording_statistics, statistics_arrays

        ds.statistics = statistics_arrays(recording_statistics(ds.contacts, ds.forces), ds.contacts, ds.forces)
    written = save_dataset(out, ds, logs=[str(p) for p in a.logs], air=[str(p) for p in a.air])
    masked: dict[str, int] = {}
    for t in trials:
        for k_, v_ in t.why_masked.items():
            masked[k_] = masked.get(k_, 0) + v_
    masked.update({k_: v_ for k_, v_ in avg.why_masked.items()})
    runs_note = f" from {len(names)} run(s) in sand" if len(names) != len(a.logs) else ""
    print(f"wrote {written}: {len(ds)} samples x {ds.contacts.n_segments} segments"
          + (" and their spectral statistics" if a.statistics else "") + runs_note)
    for line in dataset_summary(ds, masked or None, n_before=len(avg.time)):
        print(f"  {line}")
    return 0


def register(sub) -> None:
    p = sub.add_parser("ingest", help="logs -> forces -> air subtraction, filter, trial average -> dataset",
                       description="Turn motor logs of repeated trials (and in-air runs along the same path) "
                                   "into an I-RFT dataset (contacts + forces, npz). Checks the physics first and "
                                   "prints a summary.")
    p.add_argument("logs", nargs="+", help="log files of the trials in sand")
    p.add_argument("--air", nargs="*", default=[], help="log files of the same path in air")
    p.add_argument("--out", required=True, help="dataset .npz ('.npz' is appended when missing)")
    p.add_argument("--nodes", type=int, nargs=2, default=[0, 1],
                   help="node ids of motor 1 and motor 2 (MIT: the driver ids in byte 0)")
    add_protocol_args(p)
    g = p.add_argument_group("MIT mode (--protocol mit)")
    g.add_argument("--mit-model", default="AK80-9", help="AK model, sets the field ranges (default AK80-9)")
    g.add_argument("--mit-master-id", type=int, default=0, help="CAN id the replies are sent to (default 0)")
    g.add_argument("--mit-p-max", type=float, help="override: position range +-, rad")
    g.add_argument("--mit-v-max", type=float, help="override: velocity range +-, rad/s")
    g.add_argument("--mit-t-max", type=float, help="override: torque (N m) or current (A) range +-")
    g.add_argument("--mit-quantity", choices=["torque", "current"],
                   help="override: what the 12-bit field carries (current: give --kt as output-side N m per A, "
                        "i.e. gear ratio x k_t, and keep --gear-ratio 1: MIT positions are output-side)")
    p.add_argument("--rate", type=float, help="resampling rate, Hz, within 10x of the logs' own (default: the logs' "
                                              "current rate)")
    p.add_argument("--filter-window", type=int, default=5,
                   help="zero-phase moving average, samples, odd, at most a tenth of a run (default 5)")
    p.add_argument("--arc-noise", type=float, default=0.0,
                   help="toe moves below this many m add no arc length when aligning the air run and trials "
                        "(encoder jitter while standing still; default 0, about 2e-4 for a jittery leg)")
    p.add_argument("--no-statistics", dest="statistics", action="store_false",
                   help="do not save the dataset's spectral sufficient statistics (saved by default: irft fit then "
                        "skips its pass over the data; 2 x F^2 x 8 bytes, F = 289 features: 1.3 MB)")
    p.add_argument("--on-error", choices=["raise", "warn"], default="raise",
                   help="a truncated or damaged log: stop with an error (default) or use what was read")
    p.add_argument("--channel", help="read only this CAN channel of the logs (a log of several buses, candump -L "
                                     "any: 'can0'; .asc/.blf: the channel number); needed when their node ids collide")
    g = p.add_argument_group("physical checks")
    g.add_argument("--max-current", type=float, default=80.0,
                   help="|current| above this, A, is an outlier: masked and counted (default 80)")
    g.add_argument("--max-torque", type=float, default=None, help="the same for torque logs, N m (default none)")
    g.add_argument("--max-depth", type=float, default=0.15,
                   help="the toe deeper than this, m, is an error (a wrong --hip-height or --l1/--l2); default 0.15")
    g.add_argument("--path-tol", type=float, default=None,
                   help="trials and air runs must follow the same path within this RMS distance, m "
                        "(default max(1 cm, 5 %% of the path))")
    g.add_argument("--crop-trials", action="store_true",
                   help="a trial (or air run) shorter than the others: crop all to the shortest (default: an error)")
    g.add_argument("--any-medium", action="store_true",
                   help="skip the check that the forces look like a granular medium's at the stated contacts (the "
                        "sign of the lift, a scale within 0.01x to 30x the generic map's: catches swapped trial and "
                        "air runs, unit slips, a wrong --hip-height)")
    g.add_argument("--heading", type=_heading, default=0.0,
                   help="toe heading: fixed angle, rad (default 0), or link1/link2 (toe fixed to that link)")
    add_leg_args(p)
    add_toe_args(p)
    p.set_defaults(func=cmd_ingest)
