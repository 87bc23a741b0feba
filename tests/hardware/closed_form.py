"""Closed-form references for the five-bar leg, written from hardware_facts.md, independent of
irft_torch.hardware.FiveBarLeg (shared by the hardware tests; not a test module).

Coaxial leg: L(g) = l1 cos g + sqrt(l2^2 - l1^2 sin^2 g), toe (L sin th, -L cos th), q1 = th + g,
q2 = th - g; F_radial = (tau1 - tau2) / L'(g), F_tangential = (tau1 + tau2) / L; the ground force
on the toe is -(F_radial e_r + F_tangential e_t).
"""

import math

import numpy as np


def ik_coaxial(x, z, l1, l2):
    """Joint angles (rad) putting the toe at (x, z) in the leg frame (hips at the origin)."""
    L = math.hypot(x, z)
    th = math.atan2(x, -z)
    g = math.acos((l1**2 + L**2 - l2**2) / (2 * l1 * L))
    return th + g, th - g


def torques_coaxial(x, z, F, l1, l2):
    """Motor torques (N m) holding the toe against the ground force F = (F_x, F_z) (N)."""
    L = math.hypot(x, z)
    th = math.atan2(x, -z)
    g = math.acos((l1**2 + L**2 - l2**2) / (2 * l1 * L))
    dL = -l1 * math.sin(g) - l1**2 * math.sin(g) * math.cos(g) / math.sqrt(l2**2 - l1**2 * math.sin(g) ** 2)
    e_r, e_t = (math.sin(th), -math.cos(th)), (math.cos(th), math.sin(th))
    radial = -(F[0] * e_r[0] + F[1] * e_r[1])
    tangential = -(F[0] * e_t[0] + F[1] * e_t[1])
    return (tangential * L + radial * dL) / 2, (tangential * L - radial * dL) / 2


def ik_spaced(x, z, l1, l2, s):
    """Joint angles for hips at (-s/2, 0) and (+s/2, 0), knee 1 on the +x side of its hip-toe line."""
    out = []
    for hx, sign in ((-s / 2, 1), (s / 2, -1)):
        rx, rz = x - hx, z
        r = math.hypot(rx, rz)
        g = math.acos((l1**2 + r**2 - l2**2) / (2 * l1 * r))
        out.append(math.atan2(rx, -rz) + sign * g)
    return tuple(out)


def torques_numeric(x, z, F, ik):
    """tau = -J^T F with J = (dq/dp)^-1 from central differences of the closed-form IK."""
    h = 1e-6
    cols = []
    for dx, dz in ((h, 0), (0, h)):
        a, b = ik(x + dx, z + dz), ik(x - dx, z - dz)
        cols.append([(a[0] - b[0]) / (2 * h), (a[1] - b[1]) / (2 * h)])
    dq_dp = np.array(cols).T  # rows q1, q2; columns x, z
    J = np.linalg.inv(dq_dp)
    return tuple(-(J.T @ np.asarray(F)))
