"""The arm as the supervisor knows it: its kinematic model and the state it reports.

Hardware drivers, the runtime and the simulator all share these; nothing here
imports the simulator.
"""

from supervisor.arm.kinematics import N_JOINTS, IKResult, PandaKinematics
from supervisor.arm.state import RobotState

__all__ = ["N_JOINTS", "IKResult", "PandaKinematics", "RobotState"]
