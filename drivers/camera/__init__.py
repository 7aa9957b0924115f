"""Camera backends, selected by name from configuration (imported lazily)."""

from supervisor.registry import DriverEntry, DriverRegistry

CAMERAS = DriverRegistry(
    "camera",
    {
        "sim": DriverEntry("drivers.camera.sim", "SimCamera", doc="synthetic renderer bound to a robot"),
        "replay": DriverEntry("drivers.camera.replay", "ReplayCamera", doc="recorded dataset"),
        "aravis": DriverEntry("drivers.camera.aravis", "AravisCamera", extra="aravis",
                              doc="GenICam camera (GigE Vision / USB3 Vision) through Aravis 0.8"),
        "v4l2": DriverEntry("drivers.camera.v4l2", "V4L2Camera", doc="UVC / V4L2 camera through OpenCV CAP_V4L2"),
    },
)
