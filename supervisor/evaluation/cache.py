"""Localize each benchmark dataset once and cache its per-frame artifacts.

The cache file is the same CSV `supervisor localize` writes, next to a small
JSON key (hash of the dataset's metadata + frame list and of the localizer
settings); a stale or foreign cache is recomputed, never trusted.
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
from pathlib import Path

from supervisor.dataset.format import Dataset
from supervisor.errors import DatasetError
from supervisor.localization import offline
from supervisor.localization.offline import FrameArtifact
from supervisor.localization.settings import LocalizerSettings
from supervisor.outputs import write_atomic


CACHE_FORMAT = 4  # v3: + iou8 (paper 2's metric); v4: + sd_mm, sd_deg (pose uncertainty). Bump when the CSV's columns change: older caches are recomputed


def cache_key(ds: Dataset, settings: LocalizerSettings) -> str:
    h = hashlib.sha256(f"localization-cache v{CACHE_FORMAT}".encode())
    for name in ("dataset.json", "frames.csv"):
        p = ds.root / name
        if p.is_file():
            h.update(p.read_bytes())
    h.update(json.dumps(settings.to_dict(), sort_keys=True).encode())
    return h.hexdigest()


def read_artifacts(path: Path) -> list[FrameArtifact]:
    """Parse a localization.csv (units back to SI)."""
    rows = []
    with path.open(newline="") as fh:
        for r in csv.DictReader(fh):
            try:
                roi = tuple(int(v) for v in r["roi"].split("x")) if r["roi"] else None
                timings = {k: float(r[f"{k}_ms"]) / 1000 for k in ("clahe", "sift", "match", "pnp")}
                rows.append(FrameArtifact(
                    int(r["frame"]), int(r["position"]), math.radians(float(r["theta_deg"])),
                    float(r["x_mm"]) / 1000, int(r["n_inliers"]), int(r["n_matches"]), float(r["t_err_mm"]) / 1000,
                    math.radians(float(r["r_err_deg"])), float(r["reproj_px"]), r["status"],
                    float(r["latency_ms"]) / 1000, timings, roi,  # type: ignore[arg-type]
                    float(r["drift_mm"]) / 1000, math.radians(float(r["drift_deg"])),
                    float(r.get("iou8") or "nan"),
                    float(r.get("sd_mm") or "nan") / 1000, math.radians(float(r.get("sd_deg") or "nan"))))
            except (KeyError, ValueError) as exc:
                raise DatasetError(path, f"bad localization row {len(rows) + 1}: {exc}") from exc
    return rows


def localized(ds_root: Path, cache_dir: Path, settings: LocalizerSettings) -> list[FrameArtifact]:
    """Per-frame artifacts of one dataset, from the cache when its key matches."""
    ds = Dataset.open(ds_root)
    key = cache_key(ds, settings)
    csv_path = cache_dir / f"{ds.name}.csv"
    key_path = cache_dir / f"{ds.name}.key"
    if csv_path.is_file() and key_path.is_file() and key_path.read_text().strip() == key:
        return read_artifacts(csv_path)
    model = offline.model_from_dataset(ds, settings)
    rows = offline.localize_dataset(ds, model, settings)
    write_atomic(csv_path, offline.artifacts_csv(rows))
    write_atomic(key_path, key.encode())
    # Return what a later cache hit will return (the CSV's rounding), so results never depend on
    # whether the cache was warm.
    return read_artifacts(csv_path)
