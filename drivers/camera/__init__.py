"""Camera backends, selected by name from configuration (imported lazily)."""

from supervisor.registry import DriverEntry, DriverRegistry

CAMERAS = DriverRegistry(
    "camera",
    {
        "sim": DriverEntry("drivers.camera.sim", "SimCamera", doc="synthetic renderer bound to a robot"),
        "replay": DriverEntry("drivers.camera.replay", "ReplayCamera", doc="recorded dataset"),
    },
)
