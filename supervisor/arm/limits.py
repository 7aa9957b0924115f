"""Joint limit tables per Franka arm (datasheet values; rad, rad/s, rad/s^2, rad/s^3).

The Panda (FER) and the Franka Research 3 share the kinematic (DH) parameters, so
one kinematic model serves both; their joint limits differ. `robot.arm` in the
configuration picks the table (`PandaKinematics(arm=...)`).

Sources: Franka's "robot and interface specifications" (Panda: libfranka's
`kMaxJoint*` constants; FR3: "Limits for Franka Research 3"). The FR3's velocity
limit is position dependent near the range ends (libfranka
`computeUpperLimitsJointVelocity`); the table holds its constant upper bound.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ArmLimits:
    name: str
    q_min: np.ndarray
    q_max: np.ndarray
    dq_max: np.ndarray
    ddq_max: np.ndarray
    dddq_max: np.ndarray


def _table(name: str, *rows: list[float]) -> ArmLimits:
    arrays = [np.array(r, dtype=float) for r in rows]
    for a in arrays:
        a.setflags(write=False)
    return ArmLimits(name, *arrays)


PANDA = _table(
    "panda",
    [-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973],
    [2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973],
    [2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61],
    [15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0],
    [7500.0, 3750.0, 5000.0, 6250.0, 7500.0, 10000.0, 10000.0],
)

FR3 = _table(
    "fr3",
    [-2.7437, -1.7837, -2.9007, -3.0421, -2.8065, 0.5445, -3.0159],
    [2.7437, 1.7837, 2.9007, -0.1518, 2.8065, 4.5169, 3.0159],
    [2.62, 2.62, 2.62, 2.62, 5.26, 4.18, 5.26],
    [10.0] * 7,
    [5000.0] * 7,
)

ARMS: dict[str, ArmLimits] = {"panda": PANDA, "fr3": FR3}


def arm_limits(arm: str) -> ArmLimits:
    """The limit table of `arm` ('panda' or 'fr3'); ValueError for another name."""
    try:
        return ARMS[arm]
    except KeyError:
        raise ValueError(f"unknown arm {arm!r}; expected one of {', '.join(ARMS)}") from None
