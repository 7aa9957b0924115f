"""On-disk dataset format (version 1).

    DATASET/
      dataset.json        metadata: format/version, kind (arc|line), units, intrinsics,
                          T_flange_cam, scene, target (frame, board, ROI box), motion,
                          model_images (file, t, q, T_base_flange, T_cam_target_true)
      frames.csv          one row per sample frame (see FRAME_COLUMNS)
      model/model_0.png   the two model-generation images (lossless, mono8)
      model/model_1.png
      frames/p000_i00.png sample frames: position 000, image 00 (lossless, mono8)

All numbers are SI (metres, radians, seconds). Transforms are row-major 4x4.
`s` is the path coordinate: the arc angle (rad) for arcs, the travelled distance
(m) for lines. `t` is simulated or host-monotonic time in seconds. Camera poses
are not stored: `T_base_cam = T_base_flange @ T_flange_cam`.
A dataset is written to a temporary sibling directory and renamed into place
when complete, so a reader never sees half a dataset.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from supervisor.camera_model import Intrinsics
from supervisor.errors import DatasetError
from supervisor.geometry import InvalidTransform, validate_T
from supervisor.outputs import StagedOutput

FORMAT_NAME = "panda-supervisor-dataset"
FORMAT_VERSION = 1
METADATA_FILE = "dataset.json"
FRAMES_FILE = "frames.csv"
_MAT = [f"{r}{c}" for r in range(4) for c in range(4)]
FRAME_COLUMNS = (
    ["index", "position", "s", "t", "file"]
    + [f"q{j}" for j in range(1, 8)]
    + [f"T_base_flange_{m}" for m in _MAT]
    + [f"T_cam_target_true_{m}" for m in _MAT]
)
DATASET_COMMAND = "dataset generate"
DATASET_FILES = (METADATA_FILE, FRAMES_FILE, "model", "frames", "model.npz")  # what a dataset directory holds
REQUIRED_METADATA = ("format", "format_version", "kind", "intrinsics", "T_flange_cam", "model_images", "motion")


@dataclass(frozen=True)
class FrameRecord:
    """One recorded image and the robot state it was taken at."""

    index: int
    position: int
    s: float
    t: float
    file: str
    q: np.ndarray
    T_base_flange: np.ndarray
    T_cam_target_true: np.ndarray | None = None

    def T_base_cam(self, T_flange_cam: np.ndarray) -> np.ndarray:
        return self.T_base_flange @ T_flange_cam

    def to_row(self) -> list[Any]:
        gt = [""] * 16 if self.T_cam_target_true is None else [repr(float(v)) for v in self.T_cam_target_true.ravel()]
        return ([self.index, self.position, repr(float(self.s)), repr(float(self.t)), self.file]
                + [repr(float(v)) for v in self.q]
                + [repr(float(v)) for v in self.T_base_flange.ravel()] + gt)

    def to_json(self) -> dict[str, Any]:
        return {"index": self.index, "position": self.position, "s": self.s, "t": self.t, "file": self.file,
                "q": [float(v) for v in self.q], "T_base_flange": self.T_base_flange.tolist(),
                "T_cam_target_true": None if self.T_cam_target_true is None else self.T_cam_target_true.tolist()}


RIGID_TOL = 1e-4  # |R^T R - I|: recorded transforms are rigid to far better than this


def _matrix(value: Any, where: str, file: Path) -> np.ndarray:
    """A finite rigid 4x4 transform (orthonormal rotation, last row 0 0 0 1), or DatasetError at `where`."""
    try:
        m = np.asarray(value, dtype=float).reshape(4, 4)
    except (TypeError, ValueError, OverflowError) as exc:
        raise DatasetError(file, f"{where}: expected a 4x4 matrix") from exc
    try:
        return validate_T(m, where, tol=RIGID_TOL)
    except InvalidTransform as exc:
        raise DatasetError(file, str(exc)) from None


def _finite_vector(value: Any, n: int, where: str, file: Path) -> np.ndarray:
    try:
        v = np.asarray(value, dtype=float).reshape(n)
    except (TypeError, ValueError, OverflowError) as exc:
        raise DatasetError(file, f"{where}: expected {n} numbers") from exc
    if not np.all(np.isfinite(v)):
        raise DatasetError(file, f"{where}: contains NaN or inf")
    return v


def _finite(value: Any, where: str, file: Path) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise DatasetError(file, f"{where}: expected a finite number, got {str(value)[:40]!r}")
    return float(value)


def _record_from_json(d: Any, where: str, file: Path) -> FrameRecord:
    if not isinstance(d, dict):
        raise DatasetError(file, f"{where}: expected an object, got {type(d).__name__}")
    if not isinstance(d.get("file"), str) or not d["file"]:
        raise DatasetError(file, f"{where}.file: expected a file name")
    try:
        gt = d.get("T_cam_target_true")
        return FrameRecord(int(d.get("index", -1)), int(d.get("position", -1)),
                           _finite(d.get("s", 0.0), f"{where}.s", file), _finite(d["t"], f"{where}.t", file),
                           d["file"], _finite_vector(d["q"], 7, f"{where}.q", file),
                           _matrix(d["T_base_flange"], f"{where}.T_base_flange", file),
                           None if gt is None else _matrix(gt, f"{where}.T_cam_target_true", file))
    except (KeyError, TypeError, ValueError, OverflowError) as exc:
        raise DatasetError(file, f"{where}: malformed record ({exc})") from exc


def _intrinsics(value: Any, mf: Path) -> Intrinsics:
    """Positive finite focal lengths, finite principal point and distortion, a sane image size."""
    try:
        intr = Intrinsics.from_dict(value)
    except (KeyError, TypeError, ValueError, AttributeError, OverflowError) as exc:
        raise DatasetError(mf, f"malformed intrinsics ({exc})") from exc
    if not (0 < intr.width <= 100_000 and 0 < intr.height <= 100_000):
        raise DatasetError(mf, f"intrinsics: image size {intr.width}x{intr.height} out of range")
    for name in ("fx", "fy", "cx", "cy"):
        v = getattr(intr, name)
        if not math.isfinite(v) or (name in ("fx", "fy") and v <= 0):
            raise DatasetError(mf, f"intrinsics.{name}: expected a finite{' positive' if name[0] == 'f' else ''} "
                                   f"number, got {v}")
    if not all(math.isfinite(x) for x in intr.dist):
        raise DatasetError(mf, "intrinsics.dist: contains NaN or inf")
    return intr


_MOTION_NUMBERS = ("azimuth", "step", "sweep", "start_offset")
_MOTION_VECTORS = ("pivot_base", "axis_base", "direction_base")
_MOTION_TRANSFORMS = ("T_base_cam0", "T_base_cam_start")


def _check_motion(motion: Any, mf: Path) -> None:
    """The motion record's known fields, where present, are finite (replay drives the robot from them)."""
    if not isinstance(motion, dict):
        raise DatasetError(mf, f"motion: expected an object, got {type(motion).__name__}")
    for k in _MOTION_NUMBERS:
        if k in motion:
            _finite(motion[k], f"motion.{k}", mf)
    for k in ("positions", "images_per_position"):
        if k in motion and (isinstance(motion[k], bool) or not isinstance(motion[k], int) or motion[k] < 1):
            raise DatasetError(mf, f"motion.{k}: expected a positive integer, got {str(motion[k])[:40]!r}")
    for k in _MOTION_VECTORS:
        if k in motion:
            _finite_vector(motion[k], 3, f"motion.{k}", mf)
    for k in _MOTION_TRANSFORMS:
        if k in motion:
            _matrix(motion[k], f"motion.{k}", mf)


def _check_target(target: Any, mf: Path) -> None:
    """`target` is optional (real recordings may lack it), but when present it must be well-formed."""
    if target is None:
        return
    if not isinstance(target, dict):
        raise DatasetError(mf, f"target: expected an object, got {type(target).__name__}")
    from supervisor.localization.fiducial import BoardSpec

    if target.get("board") is not None:
        try:
            b = BoardSpec.from_dict(target["board"])
        except (KeyError, TypeError, ValueError, AttributeError, OverflowError) as exc:
            raise DatasetError(mf, f"target.board: malformed ChArUco board ({exc!r})") from exc
        if not (2 <= b.squares_x <= 100 and 2 <= b.squares_y <= 100 and math.isfinite(b.square_m)
                and 0 < b.marker_m < b.square_m <= 1.0):
            raise DatasetError(mf, "target.board: expected 2..100 squares each way and 0 < marker_m < square_m <= 1 m")
    rb = target.get("roi_box")
    if rb is not None:
        try:
            T = np.asarray(rb["T_target_box"], float)
            half = np.asarray(rb["half_extents"], float)
        except (KeyError, TypeError, ValueError, OverflowError) as exc:
            raise DatasetError(mf, f"target.roi_box: malformed ({exc!r})") from exc
        if T.shape != (4, 4) or half.shape != (3,) or not (np.all(np.isfinite(T)) and np.all(half > 0)
                                                             and np.all(np.isfinite(half))):
            raise DatasetError(mf, "target.roi_box: expected T_target_box 4x4 and 3 positive half_extents")
        _matrix(T, "target.roi_box.T_target_box", mf)
    rp = target.get("reference_point_m")
    if rp is not None:
        try:
            p = np.asarray(rp, float)
        except (TypeError, ValueError, OverflowError) as exc:
            raise DatasetError(mf, f"target.reference_point_m: malformed ({exc!r})") from exc
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise DatasetError(mf, f"target.reference_point_m: expected 3 finite numbers (metres), got {rp!r}")


class Dataset:
    """A recorded dataset, opened read-only and validated up front."""

    def __init__(self, root: Path, meta: dict[str, Any], frames: list[FrameRecord]) -> None:
        self.root = root
        self.meta = meta
        self.frames = frames
        mf = root / METADATA_FILE
        self.intrinsics = _intrinsics(meta["intrinsics"], mf)
        self.T_flange_cam = _matrix(meta["T_flange_cam"], "T_flange_cam", mf)
        self.model_images = [_record_from_json(d, f"model_images[{i}]", mf) for i, d in enumerate(meta["model_images"])]

    # -- opening -------------------------------------------------------------
    @classmethod
    def open(cls, root: str | Path) -> Dataset:
        root = Path(root)
        mf = root / METADATA_FILE
        if not root.is_dir():
            raise DatasetError(root, "not a dataset directory (does not exist or is not a directory)")
        if not mf.is_file():
            raise DatasetError(mf, "missing dataset metadata file")
        try:
            meta = json.loads(mf.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
            raise DatasetError(mf, f"unreadable metadata ({type(exc).__name__})") from exc
        if not isinstance(meta, dict):
            raise DatasetError(mf, "metadata must be a JSON object")
        missing = [k for k in REQUIRED_METADATA if k not in meta]
        if missing:
            raise DatasetError(mf, f"missing metadata keys: {', '.join(missing)}")
        if meta["format"] != FORMAT_NAME:
            raise DatasetError(mf, f"not a {FORMAT_NAME} (format is {meta['format']!r})")
        if meta["format_version"] != FORMAT_VERSION:
            raise DatasetError(mf, f"format version {meta['format_version']} is not supported (expected {FORMAT_VERSION})")
        if not isinstance(meta["model_images"], list) or len(meta["model_images"]) != 2:
            raise DatasetError(mf, "model_images: expected a list of 2 model-image records")
        if meta["kind"] not in ("arc", "line"):
            raise DatasetError(mf, f"kind: expected 'arc' or 'line', got {str(meta['kind'])[:40]!r}")
        for key in ("scene", "target"):
            if meta.get(key) is not None and not isinstance(meta[key], dict):
                raise DatasetError(mf, f"{key}: expected an object, got {type(meta[key]).__name__}")
        if "seed" in meta and (isinstance(meta["seed"], bool) or not isinstance(meta["seed"], int)):
            raise DatasetError(mf, f"seed: expected an integer, got {str(meta['seed'])[:40]!r}")
        _check_target(meta.get("target"), mf)
        _check_motion(meta["motion"], mf)
        _intrinsics(meta["intrinsics"], mf)
        frames = cls._read_frames(root / FRAMES_FILE)
        ds = cls(root, meta, frames)
        for rec in [*ds.model_images, *frames]:
            p = ds.path_of(rec)
            if not p.is_file():
                raise DatasetError(p, f"image file listed in the dataset is missing ({ds._where(rec)})")
        return ds

    @staticmethod
    def _read_frames(path: Path) -> list[FrameRecord]:
        if not path.is_file():
            raise DatasetError(path, "missing frame index")
        out: list[FrameRecord] = []
        try:
            with path.open(newline="", encoding="utf-8") as fh:
                reader = csv.DictReader(fh)
                if reader.fieldnames is None or list(reader.fieldnames) != FRAME_COLUMNS:
                    raise DatasetError(path, "unexpected columns (expected the version-1 frame columns)")
                for lineno, row in enumerate(reader, start=2):
                    try:
                        gt = row[FRAME_COLUMNS[-16]]
                        rec = FrameRecord(
                            int(row["index"]), int(row["position"]), float(row["s"]), float(row["t"]), row["file"],
                            np.array([float(row[f"q{j}"]) for j in range(1, 8)]),
                            np.array([float(row[f"T_base_flange_{m}"]) for m in _MAT]).reshape(4, 4),
                            None if gt == "" else np.array([float(row[f"T_cam_target_true_{m}"]) for m in _MAT]).reshape(4, 4),
                        )
                    except (TypeError, ValueError, OverflowError) as exc:
                        raise DatasetError(path, f"line {lineno}: malformed value ({exc})") from exc
                    if not (np.all(np.isfinite(rec.q)) and math.isfinite(rec.t) and math.isfinite(rec.s)):
                        raise DatasetError(path, f"line {lineno}: non-finite value")
                    _matrix(rec.T_base_flange, f"line {lineno}: T_base_flange", path)
                    if rec.T_cam_target_true is not None:
                        _matrix(rec.T_cam_target_true, f"line {lineno}: T_cam_target_true (ground truth)", path)
                    if not rec.file:
                        raise DatasetError(path, f"line {lineno}: file: expected a file name")
                    out.append(rec)
        except OSError as exc:
            raise DatasetError(path, f"unreadable ({exc})") from exc
        except (csv.Error, UnicodeDecodeError) as exc:
            raise DatasetError(path, f"not a version-1 frame index ({type(exc).__name__}: {str(exc)[:80]})") from exc
        if not out:
            raise DatasetError(path, "dataset has no frames")
        return out

    # -- access --------------------------------------------------------------
    @property
    def kind(self) -> str:
        return str(self.meta["kind"])

    @property
    def name(self) -> str:
        return self.root.name

    @property
    def reference_point(self) -> np.ndarray:
        """(3,) point of the target frame where translation errors are measured (metres);
        `target.reference_point_m`, or the target-frame origin when a recording has none."""
        rp = (self.meta.get("target") or {}).get("reference_point_m")
        return np.zeros(3) if rp is None else np.asarray(rp, float)

    @property
    def has_ground_truth(self) -> bool:
        return all(f.T_cam_target_true is not None for f in self.frames)

    def _where(self, rec: FrameRecord) -> str:
        """Where a record's file name is listed: `model_images[i].file` or the frame's line."""
        for i, m in enumerate(self.model_images):
            if m is rec:
                return f"model_images[{i}].file"
        return f"line {rec.index + 2}: file" if 0 <= rec.index < len(self.frames) and self.frames[rec.index] is rec \
            else "file"

    def path_of(self, rec: FrameRecord) -> Path:
        """The record's image path, confined to the dataset root (symlinks resolved)."""
        listed_in = self.root / (METADATA_FILE if any(m is rec for m in self.model_images) else FRAMES_FILE)
        try:
            p = (self.root / rec.file).resolve()
            root = self.root.resolve()
        except (OSError, ValueError, RuntimeError) as exc:
            raise DatasetError(listed_in, f"{self._where(rec)}: unusable image path ({type(exc).__name__})") from exc
        if root not in p.parents:
            raise DatasetError(listed_in, f"{self._where(rec)}: image path {rec.file[:80]!r} escapes the dataset root")
        return p

    def load_image(self, rec: FrameRecord) -> np.ndarray:
        """The frame's mono8 pixels; DatasetError for unreadable/truncated/wrong-size files."""
        path = self.path_of(rec)
        data = np.fromfile(path, dtype=np.uint8) if path.is_file() else None
        if data is None:
            raise DatasetError(path, "image file is missing")
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
        if img is None:
            raise DatasetError(path, "unreadable or truncated image")
        if img.ndim != 2 or img.dtype != np.uint8:
            raise DatasetError(path, f"expected a mono8 image, got {img.dtype} with shape {img.shape}")
        w, h = self.intrinsics.width, self.intrinsics.height
        if img.shape != (h, w):
            raise DatasetError(path, f"wrong image size {img.shape[1]}x{img.shape[0]}, expected {w}x{h}")
        return img

    def positions(self) -> Iterator[tuple[int, list[FrameRecord]]]:
        """(position index, its frames) in recording order."""
        groups: dict[int, list[FrameRecord]] = {}
        for f in self.frames:
            groups.setdefault(f.position, []).append(f)
        yield from sorted(groups.items())


class DatasetWriter:
    """Writes a dataset into a temporary directory and renames it into place on `finish()`."""

    def __init__(self, root: str | Path, overwrite: bool = False) -> None:
        # Checked here, before any frame is rendered: a bad location, or with `overwrite` an existing
        # directory holding anything but an earlier dataset, fails now (supervisor.outputs).
        self._staged = StagedOutput(root, DATASET_COMMAND, replace=overwrite, known=DATASET_FILES,
                                    exists_hint="choose another path, or --force to replace a dataset")
        self.root = self._staged.final
        self.overwrite = overwrite
        self._tmp = self._staged.path
        (self._tmp / "model").mkdir()
        (self._tmp / "frames").mkdir()
        self._frames: list[FrameRecord] = []
        self._models: list[FrameRecord] = []
        self._done = False

    def _write_png(self, rel: str, image: np.ndarray) -> None:
        ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
        if not ok:
            raise DatasetError(self._tmp / rel, "PNG encoding failed")
        buf.tofile(self._tmp / rel)

    def add_model_image(self, image: np.ndarray, t: float, q: np.ndarray, T_base_flange: np.ndarray,
                        T_cam_target_true: np.ndarray | None) -> None:
        rel = f"model/model_{len(self._models)}.png"
        self._write_png(rel, image)
        self._models.append(FrameRecord(len(self._models), -1, 0.0, t, rel, np.asarray(q, float),
                                        np.asarray(T_base_flange, float), T_cam_target_true))

    def add_frame(self, image: np.ndarray, position: int, image_index: int, s: float, t: float, q: np.ndarray,
                  T_base_flange: np.ndarray, T_cam_target_true: np.ndarray | None) -> None:
        rel = f"frames/p{position:03d}_i{image_index:02d}.png"
        self._write_png(rel, image)
        self._frames.append(FrameRecord(len(self._frames), position, s, t, rel, np.asarray(q, float),
                                        np.asarray(T_base_flange, float), T_cam_target_true))

    def finish(self, meta: dict[str, Any]) -> Path:
        """Write the index and metadata, then atomically move the dataset into place."""
        if len(self._models) != 2:
            raise DatasetError(self.root, f"a dataset needs exactly 2 model images, got {len(self._models)}")
        with (self._tmp / FRAMES_FILE).open("w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh)
            w.writerow(FRAME_COLUMNS)
            for rec in self._frames:
                w.writerow(rec.to_row())
        full = {"format": FORMAT_NAME, "format_version": FORMAT_VERSION,
                "units": {"length": "m", "angle": "rad", "time": "s"}, **meta,
                "model_images": [m.to_json() for m in self._models],
                "frames_file": FRAMES_FILE, "n_frames": len(self._frames),
                "n_positions": len({f.position for f in self._frames})}
        (self._tmp / METADATA_FILE).write_text(json.dumps(full, indent=1), encoding="utf-8")
        self._staged.commit()
        self._done = True
        return self.root

    def abort(self) -> None:
        if not self._done:
            self._staged.abort()
            self._done = True

    def __enter__(self) -> DatasetWriter:
        return self

    def __exit__(self, exc_type, *_: object) -> None:
        if exc_type is not None or not self._done:
            self.abort()
