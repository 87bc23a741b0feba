"""``irft ingest``: motor logs of repeated trials (and in-air runs along the same path) -> forces ->
air subtraction, zero-phase filter, trial average -> a dataset (contacts and forces), with the
physics checked first and a summary printed."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from .arguments import UsageError, _out_file, add_protocol_args, add_toe_args, make_toe


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

    def trace(path):
        data = read_log(path, nodes=set(a.nodes), on_error=a.on_error, **read_kw)
        for issue in data.issues:
            print(f"{path}: {issue}")
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            log = data.resample(tuple(a.nodes), rate=a.rate, max_current=a.max_current, max_torque=a.max_torque)
            t = forces_from_log(log, leg, motors, arc_noise=a.arc_noise)
        for w in caught:
            if "singular" not in str(w.message):
                print(f"{path}: {w.message}")
        if t.why_masked:
            print(f"{path}: masked " + "; ".join(f"{v} {k}" for k, v in t.why_masked.items()))
        return t

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
            print(f"irft ingest: {label}{w.message}")
        return out

    air_traces = [trace(p) for p in a.air]
    air = average(air_traces, a.air, "air run", "air runs: ") if air_traces else None
    trials = []
    for p in a.logs:
        t = trace(p)
        if air is not None:
            try:
                t = subtract_air(t, air, path_tol=a.path_tol)
            except ValueError as e:
                raise ValueError(f"{p}: {e}") from None
        trials.append(zero_phase_filter(t, a.filter_window))
    avg = average(trials, a.logs, "trial")
    ds = build_dataset(avg, leg, toe, a.hip_height, heading=a.heading, max_depth=a.max_depth)
    if a.statistics:
        from ..gp.statistics import recording_statistics, statistics_arrays

        ds.statistics = statistics_arrays(recording_statistics(ds.contacts, ds.forces), ds.contacts, ds.forces)
    written = save_dataset(out, ds, logs=[str(p) for p in a.logs], air=[str(p) for p in a.air])
    masked: dict[str, int] = {}
    for t in trials:
        for k_, v_ in t.why_masked.items():
            masked[k_] = masked.get(k_, 0) + v_
    masked.update({k_: v_ for k_, v_ in avg.why_masked.items()})
    print(f"wrote {written}: {len(ds)} samples x {ds.contacts.n_segments} segments"
          + (" and their spectral statistics" if a.statistics else ""))
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
    p.add_argument("--rate", type=float, help="resampling rate, Hz (default: the logs' current rate)")
    p.add_argument("--filter-window", type=int, default=5,
                   help="zero-phase moving average, samples, odd (default 5)")
    p.add_argument("--arc-noise", type=float, default=0.0,
                   help="toe moves below this many m add no arc length when aligning the air run and trials "
                        "(encoder jitter while standing still; default 0, about 2e-4 for a jittery leg)")
    p.add_argument("--no-statistics", dest="statistics", action="store_false",
                   help="do not save the dataset's spectral sufficient statistics (saved by default: irft fit then "
                        "skips its pass over the data; 2 x F^2 x 8 bytes, F = 289 features: 1.3 MB)")
    p.add_argument("--on-error", choices=["raise", "warn"], default="raise",
                   help="a truncated or damaged log: stop with an error (default) or use what was read")
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
    g.add_argument("--heading", type=_heading, default=0.0,
                   help="toe heading: fixed angle, rad (default 0), or link1/link2 (toe fixed to that link)")
    add_leg_args(p)
    add_toe_args(p)
    p.set_defaults(func=cmd_ingest)
