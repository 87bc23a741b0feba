"""``irft live``: CAN frames in, an updated terrain estimate out after every stance (``hardware.live``),
every frame logged; ``--simulate`` walks the simulated leg on a virtual bus in real time."""

from __future__ import annotations

import math
import sys
import time
import uuid
from pathlib import Path

from .arguments import MAPS, UsageError, _out_dir, add_protocol_args, add_toe_args, make_toe
from .ingest import _leg_and_motors, add_leg_args
from .record import _open_bus, add_bus_args


def _start_model(n_iter: int):
    """``start_model`` for the estimator: an ``InverseRFT`` on the first stances, fitted with the plug-in
    hyperparameters (``hyper_posterior="map"``: each later stance is one streaming update) in the spectral
    space (its cost per update does not grow with the stances seen)."""

    def build(contacts, forces):
        from ..gp import InverseRFT

        model = InverseRFT(contacts, forces, hyper_posterior="map", engine="spectral")
        model.fit(n_iter=n_iter, progress=False)
        return model

    return build


def cmd_live(a) -> int:
    import can

    from ..hardware import LiveEstimator

    if a.protocol != "odrive":
        raise UsageError("--protocol", "irft live reads ODrive CANSimple (cyclic Get_Encoder_Estimates and Get_Iq); "
                                       "MIT mode is not supported live yet (record it with irft record)")
    if not a.log_name.lower().endswith((".blf", ".asc", ".log", ".csv")):
        raise UsageError("--log-name", f"the suffix picks the log format: .blf, .asc, .log or .csv, got {a.log_name!r}")
    if a.duration is not None and not (math.isfinite(a.duration) and a.duration > 0):
        raise UsageError("--duration", f"must be positive seconds, got {a.duration:g}")
    for name in ("snapshot_period", "stale_after", "force_threshold"):
        v = getattr(a, name)
        if not (math.isfinite(v) and v > 0):
            raise UsageError("--" + name.replace("_", "-"), f"must be positive, got {v:g}")
    for name in ("warmup", "strides", "print_every"):
        if getattr(a, name) < 1:
            raise UsageError("--" + name.replace("_", "-"), f"must be a positive integer, got {getattr(a, name)}")
    if a.max_log_mb < 0:
        raise UsageError("--max-log-mb", f"must be >= 0 (0: one file), got {a.max_log_mb:g}")
    out = _out_dir(a.out, "--out") if a.out else None
    leg, motors = _leg_and_motors(a)
    toe = make_toe(a)
    model = None
    if a.model:
        from ..gp import InverseRFT

        if not Path(a.model).is_file():
            raise UsageError("--model", f"no model file at {a.model}")
        model = InverseRFT.load(a.model)
    air = None
    if a.air:
        from ..hardware import AirBaseline

        if not Path(a.air).is_file():
            raise UsageError("--air", f"no air-run log at {a.air}")
        if not (math.isfinite(a.air_distance) and 0 < a.air_distance < 100):
            raise UsageError("--air-distance", f"must be in (0, 100) mm, got {a.air_distance:g}")

        air = AirBaseline.from_log(a.air, leg, motors, firmware=a.firmware, nodes=tuple(a.nodes), rate=a.rate,
                                   filter_window=a.filter_window, max_distance=a.air_distance / 1000)
    walker = None
    if a.simulate:
        from ..hardware import WalkingLeg

        channel = f"irft-live-{uuid.uuid4().hex}-bus"
        walker = WalkingLeg(toe, MAPS[a.map](a.scale_x, a.scale_z), leg=leg, motors=motors, hip_height=a.hip_height,
                            rate=a.rate, current_noise=a.current_noise, nodes=tuple(a.nodes), firmware=a.firmware,
                            seed=a.seed)

        def factory():
            return can.Bus(channel=channel, interface="virtual")
        duration = a.duration if a.duration is not None else a.strides * walker.stride_time + 1.0
        print(f"irft live: simulated leg, {a.strides} strides of {walker.stride_time:.2f} s in {a.map} sand "
              f"(scale x {a.scale_x:g}, z {a.scale_z:g}) on a virtual bus at {a.rate:g} Hz", file=sys.stderr)
    else:
        def factory():
            return _open_bus(a)
        duration = a.duration
    bus = factory()
    json_out = sys.stdout if a.json else None
    every = max(1, a.print_every)

    def show(est) -> None:
        if a.json or est.event != "stance" or est.stance % every:
            return
        if est.used and est.why_unused is None and not math.isnan(est.scale[0]):
            print(f"stance {est.stance}: map = generic x ({est.scale[0]:.3f} ± {est.scale_std[0]:.3f}, "
                  f"{est.scale[1]:.3f} ± {est.scale_std[1]:.3f}) (x, z); residual {est.residual_rms[0]:.3g}, "
                  f"{est.residual_rms[1]:.3g} N; latency {1e3 * est.latency:.0f} ms" + (" STALE" if est.stale else ""),
                  flush=True)
        elif not est.used:
            print(f"stance {est.stance}: not used: {est.why_unused}", flush=True)

    est = LiveEstimator(bus, leg, motors, toe, a.hip_height, model=model, start_model=_start_model(a.n_iter), air=air,
                        warmup=a.warmup, callback=show, nodes=tuple(a.nodes), firmware=a.firmware, rate=a.rate,
                        filter_window=a.filter_window, stance=a.stance, force_threshold=a.force_threshold,
                        out_dir=out, log_name=a.log_name, max_log_bytes=int(a.max_log_mb * 1e6), json_stream=json_out,
                        snapshot_period=a.snapshot_period, stale_after=a.stale_after, bus_factory=factory,
                        max_current=a.max_current, progress=not a.quiet and not a.json)
    try:
        est.start()
        if walker is not None:
            walker.start(channel, a.strides)
        end = math.inf if duration is None else time.monotonic() + duration
        while time.monotonic() < end:
            time.sleep(0.05)
            if est.error is not None:
                raise est.error
            if walker is not None and not walker.running:
                est.drain(ended=True)
                break
    finally:  # Ctrl-C included: the log closed, the last snapshot written, then the interrupt goes on (exit 130)
        if walker is not None:
            walker.stop()
        est.stop()
        bus.shutdown()
        if est.last is not None and not a.json:
            print(f"irft live: {est.last.stance} stance(s); " + (f"log {est.log_path}, snapshot {est.snapshot_path}"
                                                                 if out else "nothing written (no --out)"),
                  file=sys.stderr)
    return 0


def register(sub) -> None:
    p = sub.add_parser("live", help="CAN frames in, an updated terrain estimate out after every stance, every frame "
                                    "logged",
                       description="Listen to the leg's motor controllers (ODrive CANSimple with cyclic "
                                   "Get_Encoder_Estimates and Get_Iq), and after each stance update the terrain "
                                   "estimate: printed (or --json: one JSON object per line per stance on stdout), "
                                   "model snapshots and the frame log in --out. --simulate: a simulated leg walks "
                                   "on a virtual bus in real time. Ctrl-C ends it cleanly (the log closed, the last "
                                   "snapshot written). docs/real_leg.md, 'Live'.")
    add_bus_args(p)
    p.add_argument("--nodes", type=int, nargs=2, default=[0, 1], help="node ids of motor 1 and motor 2")
    p.add_argument("--out", metavar="DIR", help="folder for the frame log, live.jsonl and model.pt snapshots")
    p.add_argument("--log-name", default="frames.blf", help="the log's file name in DIR; .blf, .asc, .log, .csv")
    p.add_argument("--max-log-mb", type=float, default=0.0, help="rotate the log at this size, MB (0: one file)")
    p.add_argument("--json", action="store_true", help="one JSON object per line per stance (and status) on stdout")
    p.add_argument("--model", help="a fitted model (irft fit's model.pt) to update; default: fit one on the first "
                                   "--warmup stances")
    p.add_argument("--warmup", type=int, default=3, help="stances the start model is fitted on (default 3)")
    p.add_argument("--n-iter", type=int, default=100, help="fit steps of the start model (default 100)")
    p.add_argument("--duration", type=float, help="stop after this many s (default: until Ctrl-C; --simulate: the "
                                                  "strides)")
    p.add_argument("--rate", type=float, default=1000.0, help="the controllers' message rate, Hz (default 1000)")
    p.add_argument("--filter-window", type=int, default=5, help="moving average, samples, odd (default 5, as ingest)")
    p.add_argument("--stance", choices=["surface", "force"], default="surface",
                   help="stance from the toe below the stated surface (default) or F_z above --force-threshold")
    p.add_argument("--force-threshold", type=float, default=1.0, help="N (--stance force; default 1)")
    p.add_argument("--snapshot-period", type=float, default=10.0, help="s between model snapshots (default 10)")
    p.add_argument("--stale-after", type=float, default=0.1, help="s of silence before the estimate is stale")
    p.add_argument("--air", metavar="LOG", help="a log of the same strides in air (irft record's air run): its force "
                   "at the toe's position is subtracted from every sample (the links' weight, friction)")
    p.add_argument("--air-distance", type=float, default=5.0,
                   help="mm: a toe farther than this from every air-run sample is masked and counted (default 5)")
    p.add_argument("--max-current", type=float, default=80.0, help="|current| above this, A, is an outlier")
    p.add_argument("--print-every", type=int, default=10, help="print every Nth stance's estimate (default 10)")
    p.add_argument("--quiet", action="store_true", help="no progress line")
    add_protocol_args(p)
    g = p.add_argument_group("simulated leg (--simulate)")
    g.add_argument("--simulate", action="store_true", help="no hardware: a simulated leg walks on a virtual bus")
    g.add_argument("--strides", type=int, default=200, help="strides to walk (default 200, 0.3 s each)")
    g.add_argument("--map", choices=sorted(MAPS), default="generic", help="the sand's stress map (default generic)")
    g.add_argument("--scale-x", type=float, default=1.0, help="multiply alpha_x (default 1)")
    g.add_argument("--scale-z", type=float, default=1.5, help="multiply alpha_z (default 1.5)")
    g.add_argument("--current-noise", type=float, default=0.05, help="current noise std, A (default 0.05)")
    g.add_argument("--seed", type=int, default=0)
    add_leg_args(p)
    add_toe_args(p)
    p.set_defaults(func=cmd_live)
