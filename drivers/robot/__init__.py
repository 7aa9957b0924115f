"""Robot backends, selected by name from configuration (imported lazily)."""

from supervisor.registry import DriverEntry, DriverRegistry

ROBOTS = DriverRegistry(
    "robot",
    {
        "sim": DriverEntry("drivers.robot.sim", "SimRobotDriver", doc="kinematic Panda in simulated time"),
        "franka": DriverEntry("drivers.robot.franka", "FrankaRobot", extra="franka",
                              doc="Franka Panda/FR3 through franky (libfranka); tested against franky-sim, not on hardware"),
    },
)
