"""Driver-specific camera settings (the `camera.aravis` and `camera.v4l2` YAML sections), parsed once.

No vendor library is imported here, so the configuration loads on machines without them.
Units at the YAML edge: microseconds (exposure), dB (gain), pixels (ROI); SI inside.
"""

from __future__ import annotations

from dataclasses import dataclass

from supervisor.yamlschema import Node

ARAVIS_PIXEL_FORMATS = ("Mono8", "Mono10", "Mono12", "Mono16", "BayerRG8", "BayerBG8", "BayerGR8", "BayerGB8",
                        "RGB8", "BGR8")
V4L2_FOURCCS = ("YUYV", "MJPG", "GREY")


@dataclass(frozen=True)
class AravisSettings:
    """How the `aravis` driver opens and configures a GenICam camera."""

    device_id: str | None = None  # Aravis device id ("Fake_1", "Basler-21712345"); None: the first device found
    address: str | None = None  # GigE Vision camera IPv4: opened directly, without discovery
    interface_address: str | None = None  # host address that reaches `address` (default: 127.0.0.1 for loopback)
    fake_interface: bool = False  # enable Aravis's in-process "Fake" interface (tests, benchmarks)
    pixel_format: str | None = None  # None: leave the camera's current format
    exposure: float | None = None  # s; None: leave as is
    gain_db: float | None = None
    roi: tuple[int, int, int, int] | None = None  # x, y, width, height [px]
    buffers: int = 8
    fault_after_timeouts: int = 3  # consecutive timed-out grabs that declare the device lost (latched)
    packet_size: int | None = None  # GigE packet size [bytes]; None: negotiated

    @classmethod
    def from_node(cls, n: Node) -> AravisSettings:
        roi = None
        if not n.is_null("roi"):
            v = n.vector("roi", 4, min=0.0, max=16384.0)
            if any(float(x) != int(x) for x in v):
                raise n.error("roi", f"expected whole pixels [x, y, width, height], got {list(v)}")
            roi = tuple(int(x) for x in v)
            if roi[2] < 16 or roi[3] < 16:
                raise n.error("roi", f"width and height must be >= 16 px, got {roi[2]}x{roi[3]}")
        pf = n.optional_string("pixel_format")
        if pf is not None and pf not in ARAVIS_PIXEL_FORMATS:
            raise n.error("pixel_format", f"expected one of {', '.join(ARAVIS_PIXEL_FORMATS)}, got {pf!r}")
        exposure_us = _optional_number(n, "exposure_us", 1.0, 1e8)
        out = cls(
            device_id=n.optional_string("device_id"),
            address=n.optional_string("address"),
            interface_address=n.optional_string("interface_address"),
            fake_interface=n.boolean("fake_interface", False),
            pixel_format=pf,
            exposure=None if exposure_us is None else exposure_us * 1e-6,
            gain_db=_optional_number(n, "gain_db", -100.0, 100.0),
            roi=roi,
            buffers=n.integer("buffers", 8, min=2, max=256),
            fault_after_timeouts=n.integer("fault_after_timeouts", 3, min=1, max=1000),
            packet_size=_optional_int(n, "packet_size", 576, 16384),
        )
        if out.address is not None:
            _check_ipv4(n, "address", out.address)
            if out.device_id is not None or out.fake_interface:
                raise n.error("address", "give either address (a GigE camera, no discovery) or device_id / "
                                         "fake_interface, not both")
        if out.interface_address is not None:
            _check_ipv4(n, "interface_address", out.interface_address)
        n.done()
        return out


@dataclass(frozen=True)
class V4L2Settings:
    """How the `v4l2` driver opens and negotiates a UVC camera."""

    device: str = "/dev/video0"
    formats: tuple[str, ...] = ("YUYV", "MJPG")  # preference order; the first the device offers at the size wins
    buffers: int = 2

    @classmethod
    def from_node(cls, n: Node) -> V4L2Settings:
        device = n.string("device", "/dev/video0")
        fmts = ["YUYV", "MJPG"] if n.is_null("formats") else n.data["formats"]
        if (not isinstance(fmts, list) or not fmts
                or not all(isinstance(f, str) and f in V4L2_FOURCCS for f in fmts)):
            raise n.error("formats", f"expected a non-empty list of {', '.join(V4L2_FOURCCS)}, got {fmts!r}")
        out = cls(device=device, formats=tuple(fmts), buffers=n.integer("buffers", 2, min=1, max=32))
        n.done()
        return out


def _optional_number(n: Node, key: str, lo: float, hi: float) -> float | None:
    if n.is_null(key):
        return None
    return n.number(key, min=lo, max=hi)


def _optional_int(n: Node, key: str, lo: int, hi: int) -> int | None:
    if n.is_null(key):
        return None
    return n.integer(key, min=lo, max=hi)


def _check_ipv4(n: Node, key: str, value: str) -> None:
    parts = value.split(".")
    if len(parts) != 4 or not all(p.isdigit() and 0 <= int(p) <= 255 for p in parts):
        raise n.error(key, f"expected an IPv4 address, got {value!r}")
