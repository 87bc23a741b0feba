"""``irft record``: log a live CAN bus (ODrive CANSimple by RTR polling, or AK MIT mode by listening)
to a python-can log, or, with ``--simulate``, a simulated leg's trials in sand and in air."""

from __future__ import annotations

import sys
from pathlib import Path

from .arguments import MAPS, UsageError, _out_file, add_path_args, add_protocol_args, add_toe_args, make_path, make_toe


def _open_bus(a):
    """python-can bus from --interface/--channel/--bitrate, with the usual failures explained."""
    import errno

    import can

    kw = {"bitrate": a.bitrate} if a.bitrate else {}
    try:
        return can.Bus(channel=a.channel, interface=a.interface, **kw)
    except can.exceptions.CanInterfaceNotImplementedError as e:
        raise UsageError("--interface", f"python-can cannot use {a.interface!r} here: {e}") from None
    except OSError as e:
        if e.errno in (errno.EAFNOSUPPORT, errno.ENODEV, errno.ENXIO):
            hint = ("socketcan is not available on this machine (Linux CAN sockets: [Errno 97])"
                    if e.errno == errno.EAFNOSUPPORT else f"no CAN device {a.channel!r}")
            raise UsageError("--interface" if e.errno == errno.EAFNOSUPPORT else "--channel",
                             f"{hint}. Bring up a device (sudo ip link set can0 up type can bitrate 1000000), try a "
                             "virtual one (sudo modprobe vcan; sudo ip link add dev vcan0 type vcan; --channel vcan0), "
                             "or record a simulated leg with --simulate") from None
        raise
    except (can.CanError, ValueError) as e:
        raise UsageError("--interface", f"cannot open {a.interface} channel {a.channel!r}: {e}") from None


def _numbered(out: Path, k: int, n: int) -> Path:
    return out if n == 1 else out.with_name(f"{out.stem}_{k + 1}{out.suffix}")


def _record_simulated(a, out: Path) -> int:
    from ..hardware import MotorModel, SimulatedLeg

    if a.protocol != "odrive":
        raise UsageError("--simulate", "the simulated leg speaks ODrive CANSimple only (use --protocol odrive)")
    air = _out_file(a.air_out, "--air-out") if a.air_out else out.with_name(f"{out.stem}_air{out.suffix}")
    if air.suffix.lower() != out.suffix.lower():
        raise UsageError("--air-out", f"use the same log format as --out ({out.suffix})")
    outs = [_numbered(out, k, a.trials) for k in range(a.trials)]
    for o in outs:  # the air run would overwrite a trial (or the other way round): refuse before writing anything
        if o.resolve() == air.resolve():
            raise UsageError("--air-out", f"{air} is also a trial's log (--out {out}"
                                          + (f", trial {outs.index(o) + 1}" if a.trials > 1 else "")
                                          + "): the run in air would overwrite it; give the air run its own name "
                                            f"(default {out.stem}_air{out.suffix})")
    toe, path = make_toe(a), make_path(a)
    sim = SimulatedLeg(toe, MAPS[a.map](a.scale_x, a.scale_z), motors=(MotorModel.u8_ii(), MotorModel.u8_ii()),
                       friction=a.friction, cogging=a.cogging, current_noise=a.current_noise,
                       frame_drop=a.frame_drop, rate=a.rate, nodes=tuple(a.nodes), firmware=a.firmware, seed=a.seed)
    for k, o in enumerate(outs):
        sim.seed = a.seed + 101 * k
        truth = sim.run(path, o)  # written whole or not at all (SimulatedLeg.run: a temporary renamed)
        print(f"wrote {o} (simulated trial in sand, {truth.time[-1]:.1f} s at {a.rate:g} Hz)")
    sim.seed = a.seed
    sim.run(path, air, in_air=True)
    print(f"wrote {air} (the same path in air)")
    toe_args = (f" --radius {a.radius} --opening {a.opening}" if a.toe == "C"
                else f" --length {a.length} --tilt {a.tilt}")
    print(f"next: irft ingest {' '.join(map(str, outs))} --air {air} --out dataset.npz --toe {a.toe}{toe_args}"
          f" --width {a.width} --segments {a.segments} --nodes {' '.join(map(str, a.nodes))} --firmware {a.firmware}")
    return 0


def cmd_record(a) -> int:
    from ..hardware import SUPPORTED_SUFFIXES, record

    out = _out_file(a.out, "--out")
    if out.suffix.lower() not in SUPPORTED_SUFFIXES:
        raise UsageError("--out", f"the suffix picks the log format; use one of {', '.join(SUPPORTED_SUFFIXES)}, "
                                  f"got {out.name!r}")
    if a.simulate:
        return _record_simulated(a, out)
    if a.protocol == "mit":
        poll: tuple = ()
        print("MIT mode: listening only (a poll would be a command); the motors' replies to your controller "
              "are logged")
    else:
        from ..hardware.bus.odrive_can import COMMANDS

        unknown = [c for c in a.poll if c not in COMMANDS[a.firmware] or not c.startswith("get_")]
        if unknown:
            raise UsageError("--poll", f"unknown Get_* command(s) {unknown} for firmware {a.firmware}; known: "
                                       f"{sorted(c for c in COMMANDS[a.firmware] if c.startswith('get_'))}")
        poll = tuple((cmd, n) for n in a.nodes for cmd in a.poll)
    bus = _open_bus(a)
    stats: dict = {}
    try:
        n = record(bus, out, duration=a.duration, poll=poll, rate=a.rate, firmware=a.firmware, stats=stats)
    finally:
        bus.shutdown()
    print(f"wrote {n} frames to {out}")
    ids = stats.get("frames_by_id", {})
    if n == 0:
        print(f"irft record: warning: no controller answered on {a.interface} channel {a.channel!r} in "
              f"{a.duration:g} s: check power, wiring, termination, the bit rate (--bitrate) and the node ids "
              "(--nodes)", file=sys.stderr)
        return 1
    if a.protocol == "odrive":
        seen = {i >> 5 for i in ids}
        silent = [nd for nd in a.nodes if nd not in seen]
        if silent:
            print(f"irft record: warning: node(s) {silent} sent no frames (nodes heard: {sorted(seen)}): check "
                  "--nodes and the controllers' CAN node ids", file=sys.stderr)
            return 1
    return 0


def add_sim_args(p) -> None:
    g = p.add_argument_group("simulated leg (with --simulate; leg l1 0.15 m, l2 0.30 m, hips 0.25 m up, U8-II)")
    g.add_argument("--simulate", action="store_true",
                   help="no hardware: a simulated leg (two fake ODrives on a virtual bus) writes --out (in sand) and "
                        "--air-out (the same path in air)")
    g.add_argument("--air-out", help="in-air log (default: OUT_air with the same suffix)")
    g.add_argument("--trials", type=int, default=1, help="trials in sand: OUT_1, OUT_2, ... when more than 1")
    g.add_argument("--map", choices=sorted(MAPS), default="generic", help="the sand's stress map (default generic)")
    g.add_argument("--scale-x", type=float, default=1.0, help="multiply alpha_x (default 1)")
    g.add_argument("--scale-z", type=float, default=1.0, help="multiply alpha_z (default 1)")
    g.add_argument("--current-noise", type=float, default=0.0, help="current noise std, A (default 0)")
    g.add_argument("--friction", type=float, default=0.0, help="Coulomb friction per motor, N m (default 0)")
    g.add_argument("--cogging", type=float, default=0.0, help="cogging ripple, N m (default 0)")
    g.add_argument("--frame-drop", type=float, default=0.0, help="probability that a frame is lost (default 0)")
    g.add_argument("--seed", type=int, default=0)


def add_bus_args(p) -> None:
    """The bus ``_open_bus`` opens: python-can interface, channel, bit rate (irft record, irft live)."""
    p.add_argument("--interface", default="socketcan", help="python-can interface (socketcan, pcan, virtual, ...)")
    p.add_argument("--channel", default="can0")
    p.add_argument("--bitrate", type=int, help="bit rate, if the interface needs it")


def register(sub) -> None:
    p = sub.add_parser("record", help="log a live CAN bus (ODrive CANSimple or AK MIT mode) to a log file",
                       description="Poll the motor controllers by RTR (ODrive) or listen (MIT mode) and write every "
                                   "frame to a log (.log, .asc, .blf, .csv by suffix). --simulate: no hardware: a "
                                   "simulated leg runs the toe along the path (its length and --speed set the "
                                   "duration; --interface, --channel, --bitrate, --duration and --poll do not apply).")
    add_bus_args(p)
    p.add_argument("--out", required=True, help="log file; the suffix picks the format (.log .asc .blf .csv)")
    p.add_argument("--duration", type=float, default=20.0, help="seconds (default 20; not with --simulate)")
    p.add_argument("--rate", type=float, default=200.0, help="polling rate, Hz (default 200)")
    p.add_argument("--nodes", type=int, nargs="+", default=[0, 1], help="controller node ids (default 0 1)")
    p.add_argument("--poll", nargs="+", default=["get_iq"], help="Get_* commands to poll (default get_iq)")
    add_protocol_args(p)
    add_sim_args(p)
    add_toe_args(p)
    add_path_args(p)
    p.set_defaults(func=cmd_record)
