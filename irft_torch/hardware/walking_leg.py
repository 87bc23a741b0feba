"""A simulated leg that walks, in real time, on python-can's virtual bus: for the live estimator what
``SimulatedLeg`` is for ``irft record``.

Each stride is a stance (the toe's lowest point dips ``depth`` m into simulated sand while it sweeps
``stride`` m backwards) and a swing (it returns ``clearance`` m above the surface). The two motors'
controllers send, every 1 / ``rate`` s of the wall clock, their encoder estimates and q-axis currents
(ODrive CANSimple Get_Encoder_Estimates and Get_Iq as cyclic messages; firmware 0.6 configures them
with ``encoder_msg_rate_ms`` / ``iq_msg_rate_ms``) and a heartbeat every 100 ms. The currents hold the
leg against the sand's force (``SimulatedLeg.truth``: rft forces, J^T, k_t), plus current noise.

Frames carry the instant the controller sampled its state (the schedule, not the moment the thread
got to send it: a host busy for 5 ms delays frames, it does not move the samples), so a run is the
same whatever the load of the machine. ``frames_sent`` counts what went on the bus; a ``hook`` sees
(and may change, drop, duplicate or hold back) each tick's frames before they are sent: the fault
tests inject their faults there.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import can
import numpy as np
import torch

from ..rft.paths import pose_path
from ..rft.toes import Toe
from .bus.odrive_can import encode
from .five_bar import FiveBarLeg
from .motor import MotorModel
from .simulated_leg import SimulatedLeg, SimulationTruth

__all__ = ["WalkingLeg", "stride_path"]


def stride_path(toe: Toe, depth: float, stride: float = 0.10, clearance: float = 0.03, stance_time: float = 0.2,
                swing_time: float = 0.1, rate: float = 1000.0):
    """One stride's toe path (``rft.Path``, world frame, z = 0 the surface): a stance in which the toe's
    lowest segment centre goes ``depth`` m deep (a half sine) while the toe sweeps from +stride/2 to
    -stride/2 (m), and a swing back ``clearance`` m above the surface; it starts and ends at the swing's
    top (the stance begins after ``swing_time / 2``). Times s, ``rate`` samples per second."""
    for name, v in (("depth", depth), ("stride", stride), ("clearance", clearance), ("stance_time", stance_time),
                    ("swing_time", swing_time), ("rate", rate)):
        if not (math.isfinite(v) and v > 0):
            raise ValueError(f"{name} must be positive, got {v}")
    lowest = float(toe.centres[:, 1].min())
    n_st, n_sw = int(round(stance_time * rate)), int(round(swing_time * rate))
    u = np.arange(n_st) / n_st
    w = np.arange(n_sw) / n_sw
    x = np.concatenate([stride / 2 - stride * u, -stride / 2 + stride * w])
    z_low = np.concatenate([-depth * np.sin(np.pi * u), clearance * np.sin(np.pi * w)])
    # start and end at the top of the swing, clearly out of contact (the stance's first sample is at the surface)
    x, z_low = np.roll(x, n_sw // 2), np.roll(z_low, n_sw // 2)
    t = np.arange(n_st + n_sw) / rate
    return pose_path(torch.as_tensor(t), torch.as_tensor(x), torch.as_tensor(z_low - lowest))


@dataclass
class WalkingLeg:
    """A five-bar leg walking through simulated sand, its controllers on a virtual CAN bus.

    Args:
        toe: the toe (rft), fixed heading 0.
        medium: the sand's stress map (e.g. ``rft.FourierStressMap.generic(1.0, 1.5)``).
        depths: the strides' depths, m, used in turn (several: the map is seen at more angles).
        stride: the toe's sweep per stance, m (``stride_path``).
        clearance: the swing's height above the surface, m.
        stance_time: s.
        swing_time: s.
        leg: kinematics, as ``SimulatedLeg``.
        motors: the two motors (k_t N m/A, directions, offsets).
        hip_height: the motor axes' height above the surface, m.
        rate: frames per motor and message per second (Hz): 1000 sends 4000 frames/s.
        current_noise: std of the measured current, A.
        nodes: the controllers' node ids (motor 1, motor 2).
        firmware: ODrive CANSimple layout, "0.5" or "0.6".
        seed: of the current noise.
        hook: ``hook(tick, frames) -> frames`` for each tick's frames (fault injection).
        air_current: ``air_current(q) -> (n, 2)`` A from joint angles (n, 2) rad: what the leg draws in air (the
            links' weight, friction), added to the currents (an air baseline's test); None: nothing.
    """

    toe: Toe
    medium: object
    depths: tuple = (0.02, 0.03, 0.025)
    stride: float = 0.10
    clearance: float = 0.03
    stance_time: float = 0.2
    swing_time: float = 0.1
    leg: FiveBarLeg = field(default_factory=lambda: FiveBarLeg(0.15, 0.30))
    motors: tuple = field(default_factory=lambda: (MotorModel.u8_ii(), MotorModel.u8_ii()))
    hip_height: float = 0.25
    rate: float = 1000.0
    current_noise: float = 0.0
    nodes: tuple = (0, 1)
    firmware: str = "0.6"
    seed: int = 0
    hook: Callable | None = None
    air_current: Callable | None = None

    def __post_init__(self) -> None:
        self.frames_sent = 0
        self._strides: list[SimulationTruth] = []
        sim = SimulatedLeg(self.toe, self.medium, leg=self.leg, motors=self.motors, hip_height=self.hip_height,
                           rate=self.rate)
        for d in self.depths:
            self._strides.append(sim.truth(stride_path(self.toe, d, self.stride, self.clearance, self.stance_time,
                                                       self.swing_time, self.rate)))
        self._air = [np.zeros((len(s.time), 2)) if self.air_current is None else
                     np.asarray(self.air_current(np.asarray(s.q)), dtype=float) for s in self._strides]
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None

    @property
    def stride_time(self) -> float:
        return self.stance_time + self.swing_time

    def stride_truth(self, k: int) -> SimulationTruth:
        """What stride ``k`` really is (its depth is ``depths[k % len(depths)]``)."""
        return self._strides[k % len(self._strides)]

    def frames(self, n_strides: int, t0: float) -> Iterator[list[can.Message]]:
        """Each tick's frames for ``n_strides`` strides from time ``t0`` (s), in order, before any hook
        (a generator: nothing is held beyond one tick): per motor, encoder estimates and current; a
        heartbeat per motor every 100 ms."""
        rng = np.random.default_rng(self.seed)
        n_per = len(self._strides[0].time)
        hb_every = max(1, int(round(0.1 * self.rate)))
        turns = [np.stack([self.motors[i].encoder_turns(torch.as_tensor(s.q[:, i])).numpy() for i in range(2)], -1)
                 for s in self._strides]
        hb = ({"axis_error": 0, "axis_state": 8, "procedure_result": 0, "trajectory_done_flag": 0}
              if self.firmware == "0.6" else
              {"axis_error": 0, "axis_state": 8, "motor_error_flag": 0, "encoder_error_flag": 0, "controller_flags": 0})
        for s in range(int(n_strides)):
            truth, pos, air = self.stride_truth(s), turns[s % len(turns)], self._air[s % len(self._air)]
            for k in range(n_per):
                tick = s * n_per + k
                now = t0 + tick / self.rate
                out = []
                for i, node in enumerate(self.nodes):
                    noise = self.current_noise * float(rng.standard_normal()) if self.current_noise else 0.0
                    iq = float(truth.current[k, i]) + float(air[k, i]) + noise
                    out.append(encode("get_encoder_estimates", node, self.firmware, now, pos_estimate=float(pos[k, i]),
                                      vel_estimate=0.0))
                    out.append(encode("get_iq", node, self.firmware, now, iq_setpoint=iq, iq_measured=iq))
                    if tick % hb_every == 0:
                        out.append(encode("heartbeat", node, self.firmware, now, **hb))
                yield out

    def walk(self, channel: str, n_strides: int, realtime: bool = True, t0: float | None = None) -> int:
        """Send ``n_strides`` strides on the virtual ``channel``, paced by the wall clock (``realtime``)
        or as fast as the bus takes them. Returns the frames sent (also ``frames_sent``)."""
        bus = can.Bus(channel=channel, interface="virtual", preserve_timestamps=True)
        t0 = time.time() if t0 is None else t0
        try:
            start = time.monotonic()
            for tick, msgs in enumerate(self.frames(n_strides, t0)):
                if self._stop.is_set():
                    break
                if realtime:
                    wait = start + tick / self.rate - time.monotonic()
                    if wait > 0:
                        time.sleep(wait)
                if self.hook is not None:
                    msgs = self.hook(tick, msgs)
                for m in msgs:
                    bus.send(m)
                    self.frames_sent += 1
        finally:
            bus.shutdown()
        return self.frames_sent

    def start(self, channel: str, n_strides: int, realtime: bool = True) -> None:
        """``walk`` in a thread (``join`` waits for it; an exception there is kept in ``error``)."""
        def run() -> None:
            try:
                self.walk(channel, n_strides, realtime)
            except BaseException as e:  # noqa: BLE001 - kept for the caller
                self.error = e

        self._stop.clear()
        self._thread = threading.Thread(target=run, name="walking-leg", daemon=True)
        self._thread.start()

    @property
    def running(self) -> bool:
        """Whether ``start``'s thread is still walking."""
        return self._thread is not None and self._thread.is_alive()

    def join(self, timeout: float | None = None) -> None:
        if self._thread is not None:
            self._thread.join(timeout)
        if self.error is not None:
            raise self.error

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
