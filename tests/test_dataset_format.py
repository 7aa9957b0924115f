"""Dataset format round trip, atomic writing, bad-input errors, and the replay camera."""

import json

import numpy as np
import pytest

from drivers.camera import CAMERAS
from drivers.camera.replay import ReplayCamera, ReplayExhausted
from supervisor.camera_model import Intrinsics
from supervisor.clock import SimClock
from supervisor.dataset.format import Dataset, DatasetWriter
from supervisor.errors import DatasetError, DriverUnavailable, OutputError
from supervisor.geometry import make_T

INTR = Intrinsics(64, 48, 60.0, 60.0, 32.0, 24.0)


def _write(root, n_pos=3, n_img=2, gt=True):
    rng = np.random.default_rng(0)
    w = DatasetWriter(root)
    T = make_T(np.eye(3), [0.3, 0.0, 0.4])
    for _ in range(2):
        w.add_model_image(rng.integers(0, 255, (48, 64), dtype=np.uint8), 0.0, np.zeros(7), T, np.eye(4))
    t = 0.0
    for p in range(n_pos):
        for i in range(n_img):
            t += 0.1
            w.add_frame(rng.integers(0, 255, (48, 64), dtype=np.uint8), p, i, 0.01 * p, t, np.full(7, 0.1 * p), T,
                        np.eye(4) if gt else None)
    return w.finish({"kind": "arc", "intrinsics": INTR.to_dict(), "T_flange_cam": np.eye(4).tolist(),
                     "motion": {"kind": "arc"}})


def test_roundtrip(tmp_path):
    root = _write(tmp_path / "ds")
    ds = Dataset.open(root)
    assert len(ds.frames) == 6 and ds.kind == "arc" and ds.has_ground_truth
    assert [p for p, _ in ds.positions()] == [0, 1, 2]
    assert ds.load_image(ds.frames[3]).shape == (48, 64)
    assert np.allclose(ds.frames[5].q, 0.2)
    assert not any(p.name.startswith(".") for p in tmp_path.iterdir())  # no partial directory left behind


def test_writer_refuses_existing_and_cleans_up_on_error(tmp_path):
    _write(tmp_path / "ds")
    with pytest.raises(OutputError, match="already exists"):
        DatasetWriter(tmp_path / "ds")
    with pytest.raises(RuntimeError):
        with DatasetWriter(tmp_path / "other"):
            raise RuntimeError("boom")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"]


def test_missing_metadata_key(tmp_path):
    root = _write(tmp_path / "ds")
    meta = json.loads((root / "dataset.json").read_text())
    del meta["intrinsics"]
    (root / "dataset.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match="dataset.json: missing metadata keys: intrinsics"):
        Dataset.open(root)


def test_other_format_version(tmp_path):
    root = _write(tmp_path / "ds")
    meta = json.loads((root / "dataset.json").read_text())
    meta["format_version"] = 99
    (root / "dataset.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match="format version 99"):
        Dataset.open(root)


def test_missing_truncated_and_wrong_size_images(tmp_path):
    root = _write(tmp_path / "ds")
    ds = Dataset.open(root)
    f0, f1 = ds.frames[0], ds.frames[1]
    p0 = ds.path_of(f0)
    p0.write_bytes(p0.read_bytes()[:40])
    with pytest.raises(DatasetError, match=r"p000_i00.png: unreadable or truncated image"):
        ds.load_image(f0)
    import cv2

    cv2.imwrite(str(ds.path_of(f1)), np.zeros((10, 10), np.uint8))
    with pytest.raises(DatasetError, match="wrong image size 10x10, expected 64x48"):
        ds.load_image(f1)
    ds.path_of(ds.frames[2]).unlink()
    with pytest.raises(DatasetError, match="missing"):
        Dataset.open(root)


def test_path_escape_rejected(tmp_path):
    root = _write(tmp_path / "ds")
    csv_path = root / "frames.csv"
    csv_path.write_text(csv_path.read_text().replace("frames/p000_i00.png", "../../etc/passwd"))
    with pytest.raises(DatasetError, match="escapes the dataset root"):
        Dataset.open(root)


def test_replay_camera_paced_and_exhausted(tmp_path):
    root = _write(tmp_path / "ds", n_pos=2, n_img=2)
    clock = SimClock(100.0)
    cam_cls = CAMERAS.load("replay")
    with cam_cls(root, clock=clock, pace="recorded") as cam:
        frames = [cam.read() for _ in range(4)]
        with pytest.raises(ReplayExhausted):
            cam.read()
    assert [f.seq for f in frames] == [1, 2, 3, 4]
    assert np.allclose(np.diff([f.t for f in frames]), 0.1)  # recorded spacing reproduced on the clock
    assert all(f.ok for f in frames) and frames[2].meta["record"].position == 1
    assert not frames[0].image.flags.writeable
    cam.close()  # idempotent


def test_unknown_driver_names_available():
    with pytest.raises(DriverUnavailable, match="unknown camera driver 'gige'.*replay"):
        CAMERAS.load("gige")


def test_reference_point_default_and_malformed(tmp_path):
    root = _write(tmp_path / "ds")
    assert np.array_equal(Dataset.open(root).reference_point, np.zeros(3))  # none recorded: frame origin
    meta = json.loads((root / "dataset.json").read_text())
    meta["target"] = {"reference_point_m": [0.01, -0.02, 0.03]}
    (root / "dataset.json").write_text(json.dumps(meta))
    assert np.allclose(Dataset.open(root).reference_point, [0.01, -0.02, 0.03])
    meta["target"] = {"reference_point_m": [0.01, "x"]}
    (root / "dataset.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=r"dataset.json: target.reference_point_m"):
        Dataset.open(root)
