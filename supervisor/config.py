"""The product configuration: YAML parsed once into frozen, validated objects.

Degrees, millimetres and Hz exist only in the YAML; everything here is SI.
Errors name the file, the dotted key and what was expected.
"""

from __future__ import annotations

import copy
import hashlib
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from supervisor.arm.limits import ARMS
from supervisor.camera_model import Intrinsics
from supervisor.errors import ConfigError
from supervisor.geometry import transform_from_config
from drivers.camera import CAMERAS
from drivers.camera.settings import AravisSettings, V4L2Settings
from drivers.robot import ROBOTS
from supervisor.localization.settings import LocalizerSettings
from supervisor.prediction.models import VARIANTS
from supervisor.stages import StageConfig, parse_stages
from supervisor.can.settings import CanSettings, parse_can

from supervisor.paths import DEFAULT_CONFIG
from supervisor.yamlschema import Node, decode_text, load_yaml_text, read_bounded


@dataclass(frozen=True)
class RobotConfig:
    driver: str
    urdf: Path | None
    control_period_s: float
    q_start: np.ndarray  # rad
    arm: str = "panda"  # panda | fr3: the joint-limit table (supervisor/arm/limits.py)
    host: str | None = None  # the controller's FCI address (robot driver franka)


@dataclass(frozen=True)
class CameraConfig:
    driver: str
    intrinsics: Intrinsics
    T_flange_cam: np.ndarray
    frame_period_s: float
    timeout_s: float
    aravis: AravisSettings = field(default_factory=AravisSettings)  # camera.aravis (driver aravis)
    v4l2: V4L2Settings = field(default_factory=V4L2Settings)  # camera.v4l2 (driver v4l2)


@dataclass(frozen=True)
class ArcProtocol:
    sweep: float  # rad
    step: float  # rad
    images_per_position: int

    @property
    def n_positions(self) -> int:
        """Positions 0, step, ..., sweep (inclusive)."""
        return int(math.floor(self.sweep / self.step + 1e-9)) + 1


@dataclass(frozen=True)
class LineProtocol:
    positions: int
    step: float  # m
    start_offsets: tuple[float, ...]  # rad, arc angle of the line's start from the model view
    images_per_position: int


@dataclass(frozen=True)
class DatasetProtocol:
    model_baseline: float  # m, camera-x translation between the two model images
    arc: ArcProtocol
    line: LineProtocol


@dataclass(frozen=True)
class RecordingConfig:
    """`recording:` sessions recorded by the daemon under `<log_dir>/sessions/` (supervisor.runtime.recorder)."""

    enabled: bool = False  # off when the section is absent; the shipped config turns it on
    quota_bytes: int = 2048 * 10**6  # all sessions together; the oldest are deleted first
    state_period_s: float = 0.01  # robot states kept in states.csv


@dataclass(frozen=True)
class Config:
    robot: RobotConfig
    camera: CameraConfig
    scene: str
    localization: LocalizerSettings
    dataset: DatasetProtocol
    file: str
    sha256: str
    stages: Mapping[str, StageConfig] = field(default_factory=dict)
    default_stage: str = ""
    can: CanSettings | None = None  # the CAN side channel (`can:`; absent or null: none)
    recording: RecordingConfig = field(default_factory=RecordingConfig)
    faults: tuple[FaultSpec, ...] = ()  # `faults:` simulator fault injection (sim drivers only; default none)
    files: tuple[Path, ...] = ()  # the `extends:` chain as read: this file first, then what it extends

    def stage(self, name: str | None = None) -> StageConfig:
        """The named stage (default: `default_stage`); an unknown name is a ConfigError."""
        name = name or self.default_stage
        if name not in self.stages:
            raise ConfigError(Path(self.file), "stages", f"unknown stage {name!r}; defined: "
                              f"{', '.join(self.stages) or 'none'}")
        return self.stages[name]


MAX_EXTENDS_DEPTH = 8  # a chain of `extends:` longer than this is refused (a cycle is named as one)


def load_config(path: str | Path | None = None) -> Config:
    """Load and validate a configuration file (default: the embedded config/default.yaml).

    A file may start from another with `extends: default` (the embedded configuration) or `extends: FILE`
    (relative to the extending file's folder): the base is loaded and validated on its own first, so an
    error in it names the base file, then the extending file's keys are laid over it (mappings merge key
    by key, anything else, lists and null included, replaces). `sha256` covers the whole chain."""
    return load_config_document(path)[0]


def load_config_document(path: str | Path | None = None) -> tuple[Config, object]:
    """`load_config`, and the merged document (units as written) the configuration was built from: the
    chain is read once, so the two (and `Config.sha256`) cannot disagree if a file changes meanwhile."""
    path = Path(path) if path is not None else DEFAULT_CONFIG
    doc, digest, files = resolve_config(path)
    return _build(copy.deepcopy(doc), path, digest, files), doc


def _build(doc: object, path: Path, digest: str, files: tuple[Path, ...]) -> Config:
    root = Node(doc, path)
    cfg = Config(
        robot=_robot(root.child("robot"), path),
        camera=_camera(root.child("camera")),
        scene=root.string("scene"),
        localization=LocalizerSettings.from_node(root.child("localization", {})),
        dataset=_dataset(root.child("dataset", {})),
        stages=_stages(root),
        default_stage=root.string("default_stage"),
        can=parse_can(root, path),
        recording=_recording(root.child("recording", {})),
        faults=_faults(root),
        file=str(path),
        sha256=digest,
        files=files,
    )
    _check_faults_on_sim(cfg, root)
    if cfg.default_stage not in cfg.stages:
        raise root.error("default_stage", f"expected one of the stages ({', '.join(cfg.stages)}), "
                                          f"got {cfg.default_stage!r}")
    root.done()
    return cfg


def resolve_config(path: str | Path | None = None) -> tuple[object, str, tuple[Path, ...]]:
    """The file's document with its `extends:` chain merged in (units as written: mm, deg, ms), the chain's
    SHA-256 and the chain's files, the given one first (the embedded default as its path). Validates
    each base on its own, not the result: `load_config` does that."""
    return _read_chain(Path(path) if path is not None else DEFAULT_CONFIG, ())


def _read_chain(path: Path, chain: tuple[Path, ...]) -> tuple[object, str, tuple[Path, ...]]:
    raw = read_bounded(path, what="configuration")
    doc = load_yaml_text(decode_text(raw, path), path)
    if not (isinstance(doc, dict) and "extends" in doc):
        return doc, hashlib.sha256(raw).hexdigest(), (path,)
    base = doc.pop("extends")
    if not isinstance(base, str) or not base.strip():
        raise ConfigError(path, "extends", "expected 'default' (the embedded configuration) or a file name, "
                                           f"got {base!r}")
    base_path = DEFAULT_CONFIG if base == "default" else (path.parent / base)
    here = path.resolve()
    if base_path.resolve() in (*chain, here):
        names = " -> ".join(str(p) for p in (*chain, here, base_path.resolve()))
        raise ConfigError(path, "extends", f"the files extend each other in a cycle: {names}")
    if len(chain) + 1 > MAX_EXTENDS_DEPTH:
        raise ConfigError(path, "extends", f"more than {MAX_EXTENDS_DEPTH} files extend one another")
    if not base_path.is_file():
        problem = "is not a regular file" if base_path.exists() else "does not exist"
        raise ConfigError(path, "extends", f"the configuration file {str(base_path)!r} {problem} "
                                           "(a relative name is taken from this file's folder)")
    base_doc, base_digest, files = _read_chain(base_path, (*chain, here))  # finds a cycle before recursing
    # the base is valid on its own (as read here, once), so an error in it names its own file
    _build(copy.deepcopy(base_doc), base_path, base_digest, files)
    merged = _overlay(base_doc, doc)
    return merged, hashlib.sha256(raw + b"\0extends\0" + base_digest.encode()).hexdigest(), (path, *files)


def _overlay(base: object, top: object) -> object:
    """`top` laid over `base`: mappings merge key by key, recursively; any other value replaces."""
    if not (isinstance(base, dict) and isinstance(top, dict)):
        return top
    out = dict(base)
    for key, value in top.items():
        out[key] = _overlay(base[key], value) if key in base else value
    return out


# -- `faults:` fault injection for the simulator drivers (issue 10) ------------------------------------
# A plan of faults the sim robot and the sim camera execute (sim/faults.py), for the daemon's fault tests.
# Never on hardware: a plan is refused unless both drivers are the simulator's.
FAULT_KINDS = {  # kind -> the sim driver that executes it
    "camera_disconnect": "camera", "frame_stall": "camera", "stale_timestamp": "camera",
    "repeated_sequence": "camera", "camera_time_backwards": "camera", "black_frame": "camera",
    "saturated_frame": "camera", "corrupted_frame": "camera", "wrong_size_frame": "camera",
    "state_gap": "robot", "nan_pose": "robot", "inf_joints": "robot", "non_orthonormal_rotation": "robot",
    "joints_out_of_limits": "robot", "robot_time_backwards": "robot", "cpu_starved": "robot",
}


@dataclass(frozen=True)
class FaultSpec:
    """One injected fault: fires once, when its trigger is met (entries fire in order: an entry's trigger
    counts only once the previous entry has ended), and stands for `duration_s` (None: from then on)."""

    kind: str
    at_angle: float | None = None  # rad: the camera's viewing angle from the scene's start view, reached moving away
    after_s: float | None = None  # s after the entry became current (the first: when the drivers opened)
    duration_s: float | None = None


def _faults(root: Node) -> tuple[FaultSpec, ...]:
    out = []
    for n in root.mappings("faults"):
        kind = n.string("kind", choices=tuple(FAULT_KINDS))
        angle, after = n.optional_number("at_angle_deg", min=0.0, max=180.0, min_exclusive=True), \
            n.optional_number("after_s", min=0.0, max=86400.0)
        if (angle is None) == (after is None):
            raise n.error("at_angle_deg", "give exactly one trigger: at_angle_deg or after_s")
        duration = n.optional_number("duration_s", min=0.0, max=86400.0, min_exclusive=True)
        n.done()
        out.append(FaultSpec(kind, None if angle is None else math.radians(angle), after, duration))
    return tuple(out)


def _check_faults_on_sim(cfg: Config, root: Node) -> None:
    if not cfg.faults:
        return
    for part, driver in (("robot", cfg.robot.driver), ("camera", cfg.camera.driver)):
        if driver != "sim":
            raise root.error("faults", f"fault injection is for the simulator only: it needs robot.driver sim and "
                                       f"camera.driver sim (got {part}.driver {driver}); faults are never injected "
                                       f"on hardware")


def _stages(root: Node) -> Mapping[str, StageConfig]:
    stages = parse_stages(root)
    for name, st in stages.items():
        if st.variant not in VARIANTS:
            raise ConfigError(root.file, f"stages.{name}.variant", f"expected one of {', '.join(VARIANTS)}, "
                              f"got {st.variant!r}")
    return stages


def _robot(n: Node, file: Path) -> RobotConfig:
    urdf = n.optional_string("urdf")
    urdf_path = None
    if urdf is not None:
        urdf_path = (file.parent / urdf).resolve()
        if not urdf_path.is_file():
            raise n.error("urdf", f"file not found: {urdf_path}")
    q = n.vector("q_start_deg", 7)
    out = RobotConfig(
        driver=n.string("driver", choices=tuple(ROBOTS.names())),
        urdf=urdf_path,
        control_period_s=1.0 / n.number("control_rate_hz", 1000.0, min=10.0, max=10000.0),
        q_start=np.radians(q),
        arm=n.string("arm", "panda", choices=tuple(ARMS)),
        host=n.optional_string("host"),
    )
    lim = ARMS[out.arm]
    outside = (out.q_start < lim.q_min) | (out.q_start > lim.q_max)
    if np.any(outside):
        j = int(np.argmax(outside))
        raise n.error("q_start_deg", f"joint {j + 1} at {q[j]:g} deg is outside the {out.arm}'s range "
                                     f"[{np.degrees(lim.q_min[j]):.2f}, {np.degrees(lim.q_max[j]):.2f}] deg")
    if out.driver == "franka" and out.host is None:
        raise n.error("host", "robot driver franka needs the controller's address (e.g. 172.16.0.2)")
    n.done()
    return out


def _camera(n: Node) -> CameraConfig:
    intr = Intrinsics(
        width=n.integer("width", min=16, max=16384),
        height=n.integer("height", min=16, max=16384),
        fx=n.number("fx", min=1.0, max=1e6),
        fy=n.number("fy", min=1.0, max=1e6),
        cx=n.number("cx", min=0.0, max=16384.0),
        cy=n.number("cy", min=0.0, max=16384.0),
        dist=tuple(n.vector("dist", 5, default=[0.0] * 5)),
    )
    if intr.cx >= intr.width or intr.cy >= intr.height:
        raise n.error("cx", f"principal point ({intr.cx}, {intr.cy}) must lie inside the {intr.width}x{intr.height} image")
    out = CameraConfig(
        driver=n.string("driver", choices=tuple(CAMERAS.names())),
        intrinsics=intr,
        T_flange_cam=transform_from_config(n, "T_flange_cam"),
        frame_period_s=1.0 / n.number("frame_rate_hz", 30.0, min=0.1, max=1000.0),
        timeout_s=n.number("timeout_ms", 200.0, min=1.0, max=60000.0) / 1000.0,
        aravis=AravisSettings.from_node(n.child("aravis", {})),
        v4l2=V4L2Settings.from_node(n.child("v4l2", {})),
    )
    n.done()
    return out


def _recording(n: Node) -> RecordingConfig:
    out = RecordingConfig(
        enabled=n.boolean("enabled", False),
        quota_bytes=int(n.number("quota_mb", 2048.0, min=0.0, max=1e9, min_exclusive=True) * 10**6),
        state_period_s=1.0 / n.number("state_rate_hz", 100.0, min=1.0, max=10000.0),
    )
    n.done()
    return out


def _dataset(n: Node) -> DatasetProtocol:
    arc = n.child("arc", {})
    arc_p = ArcProtocol(
        sweep=math.radians(arc.number("sweep_deg", 45.0, min=0.0, max=180.0, min_exclusive=True)),
        step=math.radians(arc.number("step_deg", 2.25, min=0.0, max=90.0, min_exclusive=True)),
        images_per_position=arc.integer("images_per_position", 10, min=1, max=1000),
    )
    arc.done()
    line = n.child("line", {})
    line_p = LineProtocol(
        positions=line.integer("positions", 15, min=2, max=1000),
        step=line.number("step_mm", 10.0, min=0.0, max=1000.0, min_exclusive=True) / 1000.0,
        start_offsets=tuple(math.radians(v) for v in line.number_list("start_offsets_deg", [0.0, 5.0, 10.0, 15.0],
                                                                       min=-90.0, max=90.0)),
        images_per_position=line.integer("images_per_position", 10, min=1, max=1000),
    )
    line.done()
    out = DatasetProtocol(
        model_baseline=n.number("model_baseline_mm", 20.0, min=0.0, max=500.0, min_exclusive=True) / 1000.0,
        arc=arc_p,
        line=line_p,
    )
    n.done()
    return out
