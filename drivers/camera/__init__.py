"""Camera backends, selected by name from configuration (imported lazily)."""

from supervisor.registry import DriverEntry, DriverRegistry

CAMERAS = DriverRegistry(
    "camera",
    {
        "sim": DriverEntry("drivers.camera.sim", "SimCamera", doc="synthetic renderer bound to a robot"),
        "replay": DriverEntry("drivers.camera.replay", "ReplayCamera", doc="recorded dataset"),
        "v4l2": DriverEntry("drivers.camera.v4l2", "V4L2Camera", doc="USB/UVC camera via OpenCV"),
        "aravis": DriverEntry("drivers.camera.aravis", "AravisCamera", extra="aravis", doc="GenICam via Aravis"),
    },
)
