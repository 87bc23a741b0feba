"""A simulated leg for running the whole pipeline with no hardware.

Two fake ODrive controllers sit on python-can's virtual bus and answer as real ones do: they send
heartbeats and cyclic encoder estimates and reply to RTR polls (Get_Iq, Get_Encoder_Estimates,
Get_Torques on 0.6.x). Meanwhile the leg moves its toe along a path through simulated sand whose
force comes from the rft module; the motors' currents are what holding the leg against that force
takes, plus configurable Coulomb friction, cogging ripple, current noise and dropped frames.

The simulation runs in virtual time (the bus preserves the simulated timestamps), so a 20 s run
takes well under a second.
"""

from __future__ import annotations

import math
import threading
import time
import uuid
from dataclasses import dataclass, field

import can
import numpy as np
import torch

from .._files import atomic_path
from ..rft.contacts import contacts
from ..rft.forces import forces
from ..rft.paths import Path, pose_path
from ..rft.toes import Toe
from .bus.odrive_can import COMMANDS, decode, encode
from .five_bar import FiveBarLeg
from .motor import MotorModel

__all__ = ["FakeODrive", "SimulatedLeg", "SimulationTruth"]


class FakeODrive:
    """One ODrive axis on a bus: answers RTR polls from its current state.

    Args:
        bus: its own python-can bus (e.g. a virtual bus on the host's channel).
        node: CAN node id.
        firmware: "0.5" or "0.6" frame layouts.
        drop_rate: probability that a reply or cyclic frame is lost.
    """

    def __init__(self, bus: can.BusABC, node: int, firmware: str = "0.5", drop_rate: float = 0.0,
                 seed: int = 0, torque_constant: float = 0.0973) -> None:
        self.bus, self.node, self.firmware = bus, int(node), firmware
        self.drop_rate = float(drop_rate)
        self.rng = np.random.default_rng(seed)
        self.kt = torque_constant
        self.pos = self.vel = self.iq = 0.0
        self.axis_state = 8  # closed loop
        self._last_heartbeat = -math.inf
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    def set_state(self, pos_turns: float, vel_turns: float, iq: float) -> None:
        self.pos, self.vel, self.iq = float(pos_turns), float(vel_turns), float(iq)

    def _send(self, msg: can.Message) -> None:
        if self.drop_rate and self.rng.random() < self.drop_rate:
            return
        self.bus.send(msg)

    def _reply(self, command: str, now: float) -> can.Message | None:
        kw: dict = {"firmware": self.firmware, "timestamp": now}
        if command == "get_iq":
            return encode("get_iq", self.node, iq_setpoint=self.iq, iq_measured=self.iq, **kw)
        if command == "get_encoder_estimates":
            return encode("get_encoder_estimates", self.node, pos_estimate=self.pos, vel_estimate=self.vel, **kw)
        if command == "get_torques" and "get_torques" in COMMANDS[self.firmware]:
            tq = self.iq * self.kt
            return encode("get_torques", self.node, torque_target=tq, torque_estimate=tq, **kw)
        if command == "get_bus_voltage_current":
            return encode("get_bus_voltage_current", self.node, bus_voltage=48.0, bus_current=0.0, **kw)
        return None

    def service(self, now: float) -> int:
        """Answer every pending RTR addressed to this node; return how many were answered."""
        answered = 0
        while (msg := self.bus.recv(timeout=0)) is not None:
            if not msg.is_remote_frame or msg.is_extended_id or msg.arbitration_id >> 5 != self.node:
                continue
            try:
                frame = decode(msg, self.firmware)
            except ValueError:
                continue  # a real controller ignores ids it does not know
            reply = self._reply(frame.command, now)
            if reply is not None:
                self._send(reply)
                answered += 1
        return answered

    def cyclic(self, now: float, heartbeat_period: float = 0.1) -> None:
        """The messages an ODrive sends by itself: encoder estimates, and heartbeats every 100 ms."""
        self._send(self._reply("get_encoder_estimates", now))
        if now - self._last_heartbeat >= heartbeat_period:
            self._last_heartbeat = now
            hb = {"axis_error": 0, "axis_state": self.axis_state}
            if self.firmware == "0.5":
                hb.update(motor_error_flag=0, encoder_error_flag=0, controller_flags=0)
            else:
                hb.update(procedure_result=0, trajectory_done_flag=0)
            self._send(encode("heartbeat", self.node, self.firmware, timestamp=now, **hb))

    # live mode (real time), for exercising ``record`` against a bus
    def start(self, period: float = 0.001) -> None:
        def loop():
            while not self._stop.is_set():
                self.service(time.time())
                time.sleep(period)

        self._stop.clear()
        self._thread = threading.Thread(target=loop, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread:
            self._thread.join(timeout=1.0)


@dataclass
class SimulationTruth:
    """What the simulated leg really did: time (T,) s, joint angles q (T, 2) rad, toe (T, 2) m in
    the leg frame, ground force on the toe (T, 2) N, motor currents (T, 2) A."""

    time: np.ndarray
    q: np.ndarray
    toe: np.ndarray
    force: np.ndarray
    current: np.ndarray


@dataclass
class SimulatedLeg:
    """A five-bar leg with two direct-drive motors, moving a toe through simulated sand.

    Args:
        toe: the toe geometry (rft), fixed heading.
        medium: stress map of the sand (e.g. ``FourierStressMap.generic(1.0, 1.5)``).
        leg: kinematics (default l1 = 0.15 m, l2 = 0.30 m, coaxial: it reaches the paper's 300 mm shear).
        motors: motor models (paper: U8-II, k_t = 0.0973 N m/A).
        hip_height: height of the motor axes above the sand surface, m.
        friction: Coulomb friction per motor, N m (opposes joint velocity).
        cogging: cogging ripple amplitude, N m; ``cogging_periods`` ripples per motor turn.
        current_noise: std of the measured current noise, A.
        frame_drop: probability that a frame is lost.
        rate: polling rate, Hz.
    """

    toe: Toe
    medium: object
    leg: FiveBarLeg = field(default_factory=lambda: FiveBarLeg(0.15, 0.30))
    motors: tuple = field(default_factory=lambda: (MotorModel.u8_ii(), MotorModel.u8_ii()))
    hip_height: float = 0.25
    friction: float = 0.0
    cogging: float = 0.0
    cogging_periods: int = 21
    current_noise: float = 0.0
    frame_drop: float = 0.0
    rate: float = 200.0
    nodes: tuple = (0, 1)
    firmware: str = "0.5"
    seed: int = 0

    def _trajectory(self, path: Path) -> tuple[np.ndarray, np.ndarray]:
        """Toe positions in the leg frame at the polling rate."""
        t = path.time.numpy()
        tk = np.arange(0.0, t[-1] + 1e-12, 1.0 / self.rate)
        pos = path.position.numpy()
        p = np.stack([np.interp(tk, t, pos[:, 0]), np.interp(tk, t, pos[:, 1])], -1)
        p[:, 1] -= self.hip_height
        return tk, p

    def truth(self, path: Path, in_air: bool = False) -> SimulationTruth:
        """Noise-free kinematics, ground force and the currents that hold it (plus friction, cogging)."""
        tk, p = self._trajectory(path)
        q = self.leg.inverse_kinematics(torch.as_tensor(p))
        world = pose_path(torch.as_tensor(tk), torch.as_tensor(p[:, 0]), torch.as_tensor(p[:, 1] + self.hip_height))
        f = torch.zeros(len(tk), 2, dtype=torch.float64) if in_air else forces(self.medium, contacts(self.toe, world))
        tau = self.leg.holding_torques(q, f)
        qdot = torch.as_tensor(np.gradient(q.numpy(), tk, axis=0))
        tau = tau + self.friction * torch.sign(qdot)
        current = torch.stack([self.motors[i].current(tau[:, i]) for i in range(2)], -1)
        if self.cogging:
            motor_angle = torch.stack([self.motors[i].encoder_turns(q[:, i]) for i in range(2)], -1) * 2 * math.pi
            ripple = self.cogging * torch.sin(self.cogging_periods * motor_angle)
            current = current + torch.stack([ripple[:, i] / self.motors[i].torque_constant for i in range(2)], -1)
        return SimulationTruth(tk, q.numpy(), p, f.numpy(), current.numpy())

    def run(self, path: Path, log_path, in_air: bool = False, t0: float = 1.7e9) -> SimulationTruth:
        """Run the path once and log the bus to ``log_path`` (.log/.asc/.blf/...; written to a temporary
        file renamed into place, so a failure leaves an older log whole). ``t0`` is the simulated
        wall-clock start (s since the epoch). Returns the simulation's truth."""
        truth = self.truth(path, in_air)
        with atomic_path(log_path, "log") as tmp:  # written whole or not at all: an old log stays if this fails
            self._log(truth, tmp, in_air, t0)
        return truth

    def _log(self, truth: SimulationTruth, log_path, in_air: bool, t0: float) -> None:
        rng = np.random.default_rng(self.seed + (7919 if in_air else 0))
        # no trailing digits: BLF and ASC writers read a channel number from them (a 16-bit field)
        channel = f"irft-sim-{uuid.uuid4().hex}-bus"
        host = can.Bus(channel=channel, interface="virtual", preserve_timestamps=True)
        ctrl_buses = [can.Bus(channel=channel, interface="virtual", preserve_timestamps=True) for _ in self.nodes]
        drives = [FakeODrive(b, n, self.firmware, self.frame_drop, seed=self.seed + 31 * i + (1 if in_air else 0),
                             torque_constant=self.motors[i].torque_constant)
                  for i, (b, n) in enumerate(zip(ctrl_buses, self.nodes))]
        logger = can.Logger(str(log_path))
        try:
            for k, tk in enumerate(truth.time):
                now = t0 + float(tk)
                for i, d in enumerate(drives):
                    q_i = torch.tensor(truth.q[k, i])
                    qd = (truth.q[min(k + 1, len(truth.q) - 1), i] - truth.q[max(k - 1, 0), i]) / (
                        truth.time[min(k + 1, len(truth.q) - 1)] - truth.time[max(k - 1, 0)])
                    iq = truth.current[k, i] + (self.current_noise * rng.standard_normal() if self.current_noise else 0)
                    d.set_state(float(self.motors[i].encoder_turns(q_i)),
                                float(self.motors[i].encoder_turns(torch.tensor(qd)) -
                                      self.motors[i].encoder_turns(torch.tensor(0.0))), iq)
                    d.cyclic(now)
                for n in self.nodes:
                    host.send(can.Message(arbitration_id=n << 5 | COMMANDS[self.firmware]["get_iq"][0],
                                          is_remote_frame=True, dlc=8, is_extended_id=False, timestamp=now))
                for d in drives:
                    d.service(now)  # replies carry the instant the state was sampled
                while (msg := host.recv(timeout=0)) is not None:
                    logger.on_message_received(msg)
        finally:
            logger.stop()
            host.shutdown()
            for b in ctrl_buses:
                b.shutdown()
