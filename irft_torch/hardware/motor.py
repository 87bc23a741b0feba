"""Motor model: encoder and current readings of a motor controller -> joint angle and torque.

tau_joint = direction x gear_ratio x k_t x I_q, with I_q the q-axis current a field-oriented
controller reports (ODrive ``Iq_measured``). The torque constant's convention is explicit:
ODrive's ``torque_constant = 8.27 / KV`` (8.27 = (3/2) 60 / (sqrt(3) 2 pi)) or the plain SI
``60 / (2 pi KV)``; they differ by a factor 0.866, about 15 % in force.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["MotorModel", "kt_from_kv"]


def kt_from_kv(kv: float, convention: str = "odrive") -> float:
    """Torque constant [N m / A] from a motor's KV [rpm / V].

    ``convention="odrive"``: 8.27 / KV, for the q-axis current ODrive reports (the paper's U8-II:
    KV 85 -> 0.0973). ``"si"``: 60 / (2 pi KV), the back-EMF identity for line quantities.
    """
    if not (math.isfinite(kv) and kv > 0):
        raise ValueError(f"kv must be positive (rpm/V), got {kv}")
    if convention == "odrive":
        return 8.27 / kv
    if convention == "si":
        return 60.0 / (2 * math.pi * kv)
    raise ValueError(f"convention must be 'odrive' or 'si', got {convention!r}")


@dataclass(frozen=True)
class MotorModel:
    """One joint motor.

    Args:
        torque_constant: k_t, N m / A of q-axis current, at the motor shaft.
        direction: +1 or -1, the sign between the motor's positive rotation and the leg's joint angle
            convention (counter-clockwise seen with x right, z up).
        gear_ratio: motor turns per joint turn (1 for direct drive).
        zero_offset: joint angle [rad] when the encoder reads 0 turns.
    """

    torque_constant: float
    direction: int = 1
    gear_ratio: float = 1.0
    zero_offset: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.torque_constant) and self.torque_constant > 0):
            raise ValueError(f"torque_constant must be positive (N m / A), got {self.torque_constant}")
        if self.torque_constant > 10:
            raise ValueError(f"torque_constant={self.torque_constant} N m/A is implausible for one motor")
        if self.direction not in (1, -1):
            raise ValueError(f"direction must be +1 or -1, got {self.direction}")
        if not (math.isfinite(self.gear_ratio) and self.gear_ratio > 0):
            raise ValueError(f"gear_ratio must be positive, got {self.gear_ratio}")

    @classmethod
    def from_kv(cls, kv: float, convention: str = "odrive", **kw) -> MotorModel:
        return cls(kt_from_kv(kv, convention), **kw)

    @classmethod
    def u8_ii(cls, **kw) -> MotorModel:
        """T-Motor U8-II (KV 85) as in the I-RFT paper: k_t = 0.0973 N m / A, direct drive."""
        return cls(0.0973, **kw)

    def torque(self, current) -> Tensor:
        """Joint torque [N m] from q-axis current [A]."""
        return self.direction * self.gear_ratio * self.torque_constant * torch.as_tensor(current)

    def current(self, torque) -> Tensor:
        """q-axis current [A] that gives a joint torque [N m]."""
        return torch.as_tensor(torque) / (self.direction * self.gear_ratio * self.torque_constant)

    def joint_angle(self, position_turns) -> Tensor:
        """Joint angle [rad] from the encoder position [motor turns]."""
        return self.direction * 2 * math.pi * torch.as_tensor(position_turns) / self.gear_ratio + self.zero_offset

    def encoder_turns(self, joint_angle) -> Tensor:
        """Encoder position [motor turns] at a joint angle [rad]."""
        return (torch.as_tensor(joint_angle) - self.zero_offset) * self.gear_ratio / (self.direction * 2 * math.pi)

    def joint_velocity(self, velocity_turns) -> Tensor:
        """Joint velocity [rad/s] from the encoder velocity [motor turns/s]."""
        return self.direction * 2 * math.pi * torch.as_tensor(velocity_turns) / self.gear_ratio
