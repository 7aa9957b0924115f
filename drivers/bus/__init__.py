"""CAN bus backends, selected by name from configuration (`can.interface`; imported lazily).

Every name is a python-can interface opened through one backend (`drivers.bus.pythoncan`);
`virtual` is python-can's in-process bus, the fake the tests use; `udp_multicast` carries
frames between processes (tests run it inside a private network namespace only).
"""

from supervisor.registry import DriverEntry, DriverRegistry

_BACKEND = "drivers.bus.pythoncan"

BUSES = DriverRegistry(
    "bus",
    {
        "virtual": DriverEntry(_BACKEND, "PythonCanBus", doc="python-can's in-process bus (the fake)"),
        "udp_multicast": DriverEntry(_BACKEND, "PythonCanBus", doc="frames over UDP multicast (python-can[multicast])"),
        "socketcan": DriverEntry(_BACKEND, "PythonCanBus", doc="Linux SocketCAN (can0, vcan0)"),
        "pcan": DriverEntry(_BACKEND, "PythonCanBus", doc="PEAK-System PCAN (vendor library needed)"),
        "kvaser": DriverEntry(_BACKEND, "PythonCanBus", doc="Kvaser CANlib (vendor library needed)"),
        "vector": DriverEntry(_BACKEND, "PythonCanBus", doc="Vector XL (vendor library needed)"),
        "ixxat": DriverEntry(_BACKEND, "PythonCanBus", doc="IXXAT VCI (vendor library needed)"),
        "slcan": DriverEntry(_BACKEND, "PythonCanBus", doc="serial-line CAN adapters"),
        "gs_usb": DriverEntry(_BACKEND, "PythonCanBus", doc="candleLight / gs_usb adapters"),
    },
)
