"""The Traveler leg (a symmetric direct-drive five-bar, Qian lab): its geometry and its controller's logs.

Log format (the controller's CSV): line 1 the trial protocol's setting names, line 2 their values,
line 3 the column names, then one row of numbers per sample. ``read_traveler_log`` reads it; the
data are not part of this package, point it at a file.

Geometry: proximal links 0.1 m, distal links 0.2 m, coaxial motors, and a 0.05 m extension of the
leg beyond the distal joint along the leg axis (``TRAVELER_LEG``, a ``FiveBarLeg``).

Mapping the log to this package's conventions (``FiveBarLeg``: q from straight down,
counter-clockwise positive, knee 1 on the +x side; world x right, z up, origin at the hip axis):

- joint angles q = (pi - position, pi - position1): with it ``TRAVELER_LEG.forward_kinematics(q)``
  reproduces the log's ``toe_position_x``, ``toe_position_y`` (x as logged, y up) to float32
  precision.
- torques: the package's statics F = -J^-T tau with tau = (-torque, torque1) [N m] give the force of
  the ground on the toe, (F_x, F_z). The sign is read from the data, not assumed: with it the
  stationary leg in air feels a downward force (the links' weight) and pressing into the sand
  pushes the toe up, growing with depth.
- the controller's own ``toeforce_x``, ``toeforce_y`` then equal (F_x, -F_z): its vertical component
  is the force of the toe on the ground (positive when the sand pushes up it is negative), its
  horizontal one that of the ground on the toe. ``controller_ground_force`` applies that mapping.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from .five_bar import FiveBarLeg

__all__ = ["TRAVELER_LEG", "TravelerLog", "TravelerLogError", "read_traveler_log"]

#: The Traveler's geometry (controller source: L1 = 0.1, L2 = 0.2, L3 = 0.05 m, coaxial motors).
TRAVELER_LEG = FiveBarLeg(l1=0.10, l2=0.20, hip_spacing=0.0, extension=0.05)

_REQUIRED = ("time", "toeforce_x", "toeforce_y", "toe_position_x", "toe_position_y", "position",
             "position1", "torque", "torque1")


class TravelerLogError(ValueError):
    """A Traveler log that cannot be read; the message names the file, the line and what was expected.
    ``partial`` is the TravelerLog of the rows read before the fault (None if there were none)."""

    def __init__(self, message: str, partial: TravelerLog | None = None) -> None:
        super().__init__(message)
        self.partial = partial


def _number(text: str):
    try:
        return float(text)
    except ValueError:
        return text.strip()


@dataclass
class TravelerLog:
    """One Traveler trial.

    Attributes:
        protocol: the trial's settings (line 1 names, line 2 values; numbers as float), e.g.
            ``ground_height`` (cm below the hip).
        columns: the data column names, in file order.
        data: (n, len(columns)) float64 array.
        path: where it was read from.
    """

    protocol: dict
    columns: list[str]
    data: np.ndarray
    path: Path | None = None
    _index: dict = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self._index = {c: i for i, c in enumerate(self.columns)}
        missing = [c for c in _REQUIRED if c not in self._index]
        if missing:
            raise TravelerLogError(f"{self.path or 'log'}: missing column(s) {missing}; has {self.columns}")

    def __len__(self) -> int:
        return self.data.shape[0]

    def __getitem__(self, name: str) -> np.ndarray:
        if name not in self._index:
            raise KeyError(f"no column {name!r}; columns are {self.columns}")
        return self.data[:, self._index[name]]

    @property
    def time(self) -> np.ndarray:
        return self["time"]

    @property
    def ground_height(self) -> float:
        """The protocol's ``ground_height``: the sand surface's depth below the hip, m (stated as cm)."""
        if "ground_height" not in self.protocol:
            raise KeyError("the protocol has no ground_height")
        return float(self.protocol["ground_height"]) / 100.0

    def joint_angles(self) -> Tensor:
        """(n, 2) q in FiveBarLeg's convention, rad: (pi - position, pi - position1)."""
        return torch.as_tensor(np.stack([math.pi - self["position"], math.pi - self["position1"]], -1))

    def joint_torques(self) -> Tensor:
        """(n, 2) tau for ``FiveBarLeg.ground_force`` (N m): (-torque, torque1); see the module doc."""
        return torch.as_tensor(np.stack([-self["torque"], self["torque1"]], -1))

    def toe_position(self) -> Tensor:
        """(n, 2) the controller's toe position (x, z), m, hip frame, z up."""
        return torch.as_tensor(np.stack([self["toe_position_x"], self["toe_position_y"]], -1))

    def controller_force(self) -> Tensor:
        """(n, 2) the controller's (toeforce_x, toeforce_y) as logged, N."""
        return torch.as_tensor(np.stack([self["toeforce_x"], self["toeforce_y"]], -1))

    def controller_ground_force(self) -> Tensor:
        """(n, 2) the controller's force mapped to the force of the ground on the toe: (x, -y)."""
        return self.controller_force() * torch.tensor([1.0, -1.0], dtype=torch.float64)

    def ground_force(self, leg: FiveBarLeg = TRAVELER_LEG, warn: bool = True) -> tuple[Tensor, Tensor]:
        """The package's statics on this log: force of the ground on the toe (n, 2) [N] and a validity mask."""
        return leg.ground_force(self.joint_angles(), self.joint_torques(), warn=warn)


def read_traveler_log(path) -> TravelerLog:
    """Read a Traveler controller log (two protocol lines, a header, numeric rows).

    Blank lines are ignored. Any other row that does not hold one number per column, a non-finite
    value, or a last line without a line end (a file cut mid-row) raises ``TravelerLogError`` with
    its line number and ``partial`` = the rows before it (nothing is dropped silently).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no Traveler log at {path}")
    text = path.read_bytes().decode("utf-8", errors="replace")
    lines = text.splitlines()
    content = [(i + 1, ln) for i, ln in enumerate(lines) if ln.strip()]
    if len(content) < 3:
        raise TravelerLogError(f"{path}: expected two protocol lines and a header line, found {len(content)} "
                               "non-empty line(s)")
    (_, names), (ln2, values), (ln3, header) = content[:3]
    names = [n.strip() for n in names.split(",")]
    vals = [v.strip() for v in values.split(",")]
    if len(vals) < len(names):
        raise TravelerLogError(f"{path}: line {ln2}: {len(vals)} protocol values for {len(names)} names on line 1")
    # The controller writes one more value than names (a leading unnamed one): names align from the
    # right (so ``ground_height`` gets the value the toe positions confirm); extras are kept as
    # "unnamed_0", "unnamed_1", ...
    extra = len(vals) - len(names)
    protocol = {f"unnamed_{i}": _number(v) for i, v in enumerate(vals[:extra])}
    protocol.update({n: _number(v) for n, v in zip(names, vals[extra:])})
    columns = [c.strip() for c in header.split(",")]
    if any(isinstance(_number(c), float) for c in columns):
        raise TravelerLogError(f"{path}: line {ln3} should be the column names, got numbers: {header[:80]!r}")
    rows: list[list[float]] = []

    def fail(message: str):
        partial = None
        if rows:
            try:
                partial = TravelerLog(protocol, columns, np.asarray(rows, dtype=np.float64), path)
            except TravelerLogError:
                partial = None
        kept = f"; kept the {len(rows)} row(s) before it (.partial)" if partial is not None else ""
        return TravelerLogError(f"{path}: {message}{kept}", partial)

    for lineno, ln in content[3:]:
        parts = [p.strip() for p in ln.split(",")]
        if parts and parts[-1] == "" and len(parts) == len(columns) + 1:
            parts = parts[:-1]  # a trailing comma
        if len(parts) != len(columns):
            raise fail(f"line {lineno}: {len(parts)} values, expected {len(columns)}")
        try:
            row = [float(p) for p in parts]
        except ValueError:
            raise fail(f"line {lineno}: not all numbers: {ln[:80]!r}") from None
        if not all(math.isfinite(v) for v in row):
            raise fail(f"line {lineno}: non-finite value(s): {ln[:80]!r}")
        if lineno == len(lines) and not text.endswith(("\n", "\r")):
            raise fail(f"line {lineno}: the last line has no line end (the file was cut mid-row)")
        rows.append(row)
    if not rows:
        raise TravelerLogError(f"{path}: no data rows after the header")
    data = np.asarray(rows, dtype=np.float64)
    return TravelerLog(protocol=protocol, columns=columns, data=data, path=path)
