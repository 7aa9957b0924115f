"""Localizer and target-model settings: the `localization:` YAML section, parsed once.

Every field is validated at load time (`LocalizerSettings.from_node`); errors carry
the file and the dotted key. Pixel units stay pixels; angles are radians and
distances metres in code (the YAML uses `_deg` / `_mm` suffixes for those).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

from supervisor.yamlschema import Node

MATCHERS = ("flann", "bf")
PNP_METHODS = ("usac_magsac", "epnp", "p3p", "ap3p", "iterative")
ROI_MODES = ("predicted", "off")
REFINE_MODES = ("robust", "inliers")


@dataclass(frozen=True)
class ModelSettings:
    """How the target model is built from the two model images (offline, accuracy over speed)."""

    ratio: float = 0.7  # Lowe ratio for image-0 <-> image-1 matches (mutual matches only)
    max_reprojection_px: float = 1.0  # reject a triangulated point above this error in either view
    min_parallax: float = math.radians(0.5)  # rad, angle between the two viewing rays
    min_depth: float = 0.05  # m, along camera-0 z
    max_depth: float = 3.0  # m
    min_points: int = 20  # fewer surviving points -> ModelBuildError
    # Refine each match's image-1 position by normalised cross-correlation of the image-0 patch
    # (sub-pixel peak): SIFT keypoint positions are good to ~0.3 px, which with a 2 cm baseline
    # at 0.35 m is ~1.3 mm of depth noise per point; patch refinement cuts it several-fold.
    subpixel_refine: bool = True
    refine_min_score: float = 0.8  # NCC peak below this -> the match is dropped
    # Beyond the paper: after this many sampling positions (the warm-up), re-triangulate the model
    # points from every frame so far, seen from the robot's kinematic camera poses (see
    # localization/refine.py). 0 = off (the paper's two-view model throughout).
    refine_positions: int = 0
    # After the warm-up, keep collecting and re-triangulate again at every later position (each
    # refit uses every frame so far, gated by the kinematic pose against the *original* model).
    # False: refine once after the warm-up and keep that model.
    refine_continuous: bool = False

    @classmethod
    def from_node(cls, node: Node) -> ModelSettings:
        d = cls()
        out = cls(
            ratio=node.number("ratio", d.ratio, min=0.0, max=1.0, min_exclusive=True),
            max_reprojection_px=node.number("max_reprojection_px", d.max_reprojection_px, min=0.0, max=100.0,
                                            min_exclusive=True),
            min_parallax=math.radians(node.number("min_parallax_deg", math.degrees(d.min_parallax), min=0.0,
                                                  max=90.0)),
            min_depth=node.number("min_depth_mm", d.min_depth * 1000.0, min=0.0, min_exclusive=True) / 1000.0,
            max_depth=node.number("max_depth_mm", d.max_depth * 1000.0, min=0.0, min_exclusive=True) / 1000.0,
            min_points=node.integer("min_points", d.min_points, min=4, max=1_000_000),
            subpixel_refine=node.boolean("subpixel_refine", d.subpixel_refine),
            refine_min_score=node.number("refine_min_score", d.refine_min_score, min=-1.0, max=1.0),
            refine_positions=node.integer("refine_positions", d.refine_positions, min=0, max=10_000),
            refine_continuous=node.boolean("refine_continuous", d.refine_continuous),
        )
        if out.max_depth <= out.min_depth:
            raise node.error("max_depth_mm", f"must be > min_depth_mm ({out.min_depth * 1000:g}), "
                                             f"got {out.max_depth * 1000:g}")
        node.done()
        return out


@dataclass(frozen=True)
class LocalizerSettings:
    """Per-frame localization (CLAHE -> SIFT -> ratio-test matching -> PnP-RANSAC) and model building."""

    clahe_clip: float = 2.0
    clahe_tile: int = 8  # tiles per image side
    sift_nfeatures: int = 0  # 0 = keep all
    sift_octave_layers: int = 3
    sift_contrast_threshold: float = 0.04
    sift_edge_threshold: float = 10.0
    sift_sigma: float = 1.6
    ratio: float = 0.8  # Lowe ratio test, frame -> model
    matcher: str = "flann"  # flann | bf
    flann_trees: int = 4
    flann_checks: int = 64
    pnp: str = "usac_magsac"  # usac_magsac | epnp | p3p | ap3p | iterative
    ransac_reprojection_px: float = 2.0
    ransac_iterations: int = 1000
    ransac_confidence: float = 0.999
    min_inliers: int = 6  # below: LOST (RANSAC fits only false matches)
    # Final pose polish after RANSAC. "robust": Cauchy-weighted Gauss-Newton over *all* ratio-test
    # matches, started at RANSAC's pose (a hard inlier set at 2 px keeps biased matches at full weight
    # and drops good ones just outside); "inliers": OpenCV's LM on RANSAC's inliers only.
    refine: str = "robust"
    refine_scale_px: float = 0.7  # Cauchy scale: residuals well above it get little weight
    # Guided matching (beyond the paper): after the polish, match each model point to the keypoints
    # within this radius of its projection (descriptor ratio test among those candidates) and polish
    # again on those matches. 0 = off. n_i stays RANSAC's count.
    guided_radius_px: float = 0.0
    guided_ratio: float = 0.9
    roi: str = "predicted"  # predicted | off
    roi_margin_px: int = 48
    threads: int = 0  # cv2.setNumThreads at Localizer construction; 0 = leave OpenCV's setting
    model: ModelSettings = field(default_factory=ModelSettings)

    def __post_init__(self) -> None:
        # Direct construction (tests, dataclasses.replace) gets the same checks as YAML.
        if self.matcher not in MATCHERS:
            raise ValueError(f"matcher must be one of {MATCHERS}, got {self.matcher!r}")
        if self.pnp not in PNP_METHODS:
            raise ValueError(f"pnp must be one of {PNP_METHODS}, got {self.pnp!r}")
        if self.roi not in ROI_MODES:
            raise ValueError(f"roi must be one of {ROI_MODES}, got {self.roi!r}")
        if not 0.0 < self.ratio <= 1.0:
            raise ValueError(f"ratio must be in (0, 1], got {self.ratio}")
        if self.min_inliers < 4:
            raise ValueError(f"min_inliers must be >= 4, got {self.min_inliers}")
        if self.refine not in REFINE_MODES:
            raise ValueError(f"refine must be one of {REFINE_MODES}, got {self.refine!r}")
        if not self.refine_scale_px > 0.0:
            raise ValueError(f"refine_scale_px must be > 0, got {self.refine_scale_px}")
        if not (math.isfinite(self.guided_radius_px) and self.guided_radius_px >= 0.0):
            raise ValueError(f"guided_radius_px must be >= 0, got {self.guided_radius_px}")
        if not 0.0 < self.guided_ratio <= 1.0:
            raise ValueError(f"guided_ratio must be in (0, 1], got {self.guided_ratio}")

    @classmethod
    def from_node(cls, node: Node) -> LocalizerSettings:
        """Parse and validate the `localization:` section (absent keys take the defaults)."""
        d = cls()
        out = cls(
            clahe_clip=node.number("clahe_clip", d.clahe_clip, min=0.0, max=1000.0),
            clahe_tile=node.integer("clahe_tile", d.clahe_tile, min=1, max=256),
            sift_nfeatures=node.integer("sift_nfeatures", d.sift_nfeatures, min=0, max=1_000_000),
            sift_octave_layers=node.integer("sift_octave_layers", d.sift_octave_layers, min=1, max=10),
            sift_contrast_threshold=node.number("sift_contrast_threshold", d.sift_contrast_threshold, min=0.0,
                                                max=1.0),
            sift_edge_threshold=node.number("sift_edge_threshold", d.sift_edge_threshold, min=1.0, max=1000.0),
            sift_sigma=node.number("sift_sigma", d.sift_sigma, min=0.1, max=10.0),
            ratio=node.number("ratio", d.ratio, min=0.0, max=1.0, min_exclusive=True),
            matcher=node.string("matcher", d.matcher, choices=MATCHERS),
            flann_trees=node.integer("flann_trees", d.flann_trees, min=1, max=64),
            flann_checks=node.integer("flann_checks", d.flann_checks, min=1, max=100_000),
            pnp=node.string("pnp", d.pnp, choices=PNP_METHODS),
            ransac_reprojection_px=node.number("ransac_reprojection_px", d.ransac_reprojection_px, min=0.0,
                                               max=100.0, min_exclusive=True),
            ransac_iterations=node.integer("ransac_iterations", d.ransac_iterations, min=1, max=1_000_000),
            ransac_confidence=node.number("ransac_confidence", d.ransac_confidence, min=0.0, max=1.0,
                                          min_exclusive=True),
            min_inliers=node.integer("min_inliers", d.min_inliers, min=4, max=100_000),
            refine=node.string("refine", d.refine, choices=REFINE_MODES),
            refine_scale_px=node.number("refine_scale_px", d.refine_scale_px, min=0.0, max=100.0,
                                        min_exclusive=True),
            guided_radius_px=node.number("guided_radius_px", d.guided_radius_px, min=0.0, max=100.0),
            guided_ratio=node.number("guided_ratio", d.guided_ratio, min=0.0, max=1.0, min_exclusive=True),
            roi=node.string("roi", d.roi, choices=ROI_MODES),
            roi_margin_px=node.integer("roi_margin_px", d.roi_margin_px, min=0, max=10_000),
            threads=node.integer("threads", d.threads, min=0, max=256),
            model=ModelSettings.from_node(node.child("model", {})),
        )
        node.done()
        return out

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able values (SI units) for metadata and reports."""
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> LocalizerSettings:
        """Inverse of `to_dict` (used when reading a model's metadata)."""
        d = dict(d)
        model = ModelSettings(**d.pop("model", {}))
        return cls(**d, model=model)
