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
REFINE_MODES = ("robust", "inliers", "evolution")
EVOLUTION_PARAMS = ("delta", "sigma", "lambda", "scale", "tau", "alpha")  # order of the evolution functions
EVOLUTION_SCHEDULES = ("linear", "guided")
EVOLUTION_PROGRESS = ("quality", "quality_or_rounds")


@dataclass(frozen=True)
class EvolutionSettings:
    """`localization.evolution`: viewpoint-evolution refinement (supervisor/localization/evolution.py).

    Defaults are the paper's (Zhao et al. 2024, §3.1 (2)): P 10 x C 5, lambda 0.5 -> 0.05,
    s 0.10 -> 0.001, tau 20 deg -> 0, alpha 0.3 -> 0, sigma 25 -> 5 px, termination 4.0,
    {vp_q0, vp_q1} = {0.1, 0.7}. Values the paper does not give are marked (ours).
    """

    parents: int = 10
    children: int = 5
    lambda_range: tuple[float, float] = (0.5, 0.05)  # migration factor, initial -> final
    scale_range: tuple[float, float] = (0.10, 0.001)  # scale disturbance s
    tau_range: tuple[float, float] = (math.radians(20.0), 0.0)  # cone angle, rad
    alpha_range: tuple[float, float] = (0.3, 0.0)  # relaxed-projection factor
    sigma_range: tuple[float, float] = (25.0, 5.0)  # search radius, px
    termination: float = 4.0  # eps: stop when the parents' mean quality reaches min(eps * initial, 1)
    vpq: tuple[float, float] = (0.1, 0.7)  # ridge-function measurement points {vp_q0, vp_q1}
    explore_probability: float = 0.2  # p_e (ours: the paper gives no value)
    sectors: int = 8  # slope ranges of the direction advantage (ours)
    max_rounds: int = 12  # the paper caps rounds at 11 (Table 5) and reports 8-12 on average
    patience: int = 4  # rounds without a better candidate before stopping (ours)
    lm_iterations: int = 8  # Huber-LM steps per recorded trajectory (ours)
    huber_px: float = 1.0  # (ours)
    init_rotation: float = math.radians(0.5)  # rad, ellipsoid of the initial population (ours)
    init_translation: float = 0.002  # m (ours)
    budget: float = 0.25  # s of wall time per frame; 0 = unlimited (then fully deterministic)
    seed: int = 0
    schedule: str = "linear"  # linear | guided
    # The evolution functions' abscissa: "quality" (the paper) = the population's quality between its initial
    # value and min(termination * initial, 1); "quality_or_rounds" (ours) = at least the fraction of max_rounds
    # done, so the schedules anneal even from a start whose quality already makes that range unreachable.
    progress: str = "quality"
    guided_model: str = ""  # the fitted guided model's file (schedule guided)
    guided_b: tuple[float, ...] = ()  # its exponents and correlation matrix, read from that file at load time
    guided_W: tuple[tuple[float, ...], ...] = ()

    def __post_init__(self) -> None:
        if self.parents < 2 or self.children < 1:
            raise ValueError(f"evolution needs parents >= 2 and children >= 1, got {self.parents}, {self.children}")
        if self.schedule not in EVOLUTION_SCHEDULES:
            raise ValueError(f"evolution schedule must be one of {EVOLUTION_SCHEDULES}, got {self.schedule!r}")
        if self.schedule == "guided" and not self.guided_b:
            raise ValueError("evolution schedule 'guided' needs a fitted guided model (guided_model: FILE)")
        if self.progress not in EVOLUTION_PROGRESS:
            raise ValueError(f"evolution progress must be one of {EVOLUTION_PROGRESS}, got {self.progress!r}")
        if not self.termination > 1.0:
            raise ValueError(f"evolution termination must be > 1, got {self.termination}")
        if not self.budget >= 0.0:
            raise ValueError(f"evolution budget must be >= 0, got {self.budget}")

    def initial_final(self) -> dict[str, tuple[float, float]]:
        """(initial, final) of every evolution function but delta (whose initial value is per frame)."""
        return {"sigma": self.sigma_range, "lambda": self.lambda_range, "scale": self.scale_range,
                "tau": self.tau_range, "alpha": self.alpha_range}

    @classmethod
    def from_node(cls, node: Node) -> EvolutionSettings:
        d = cls()

        def pair(key: str, default: tuple[float, float], scale: float = 1.0, **kw: float) -> tuple[float, float]:
            v = node.vector(key, 2, [x / scale for x in default], **kw)
            return (float(v[0]) * scale, float(v[1]) * scale)

        schedule = node.string("schedule", d.schedule, choices=EVOLUTION_SCHEDULES)
        guided = node.optional_string("guided_model")
        b: tuple[float, ...] = ()
        W: tuple[tuple[float, ...], ...] = ()
        if schedule == "guided":
            if guided is None:
                raise node.error("guided_model", "required when schedule is guided (fit one with "
                                                 "`supervisor evolution fit-guided`)")
            from pathlib import Path

            from supervisor.localization.evolution import GuidedModel

            path = Path(guided)
            if not path.is_absolute() and node.file is not None:
                path = Path(node.file).parent / path
            gm = GuidedModel.load(path)
            b, W = gm.b, gm.W
        out = cls(
            parents=node.integer("parents", d.parents, min=2, max=1000),
            children=node.integer("children", d.children, min=1, max=1000),
            lambda_range=pair("lambda", d.lambda_range, min=0.0, max=1.0),
            scale_range=pair("scale", d.scale_range, min=0.0, max=10.0),
            tau_range=pair("tau_deg", d.tau_range, math.radians(1.0), min=0.0, max=90.0),
            alpha_range=pair("alpha", d.alpha_range, min=0.0, max=1.0),
            sigma_range=pair("sigma_px", d.sigma_range, min=0.1, max=1000.0),
            termination=node.number("termination", d.termination, min=1.0, max=1000.0, min_exclusive=True),
            vpq=pair("vpq", d.vpq, min=0.0, max=1.0),
            explore_probability=node.number("explore_probability", d.explore_probability, min=0.0, max=1.0),
            sectors=node.integer("sectors", d.sectors, min=1, max=64),
            max_rounds=node.integer("max_rounds", d.max_rounds, min=1, max=1000),
            patience=node.integer("patience", d.patience, min=1, max=1000),
            lm_iterations=node.integer("lm_iterations", d.lm_iterations, min=1, max=1000),
            huber_px=node.number("huber_px", d.huber_px, min=0.0, max=100.0, min_exclusive=True),
            init_rotation=math.radians(node.number("init_rotation_deg", math.degrees(d.init_rotation), min=0.0,
                                                   max=45.0)),
            init_translation=node.number("init_translation_mm", d.init_translation * 1000, min=0.0,
                                         max=1000.0) / 1000.0,
            budget=node.number("budget_ms", d.budget * 1000, min=0.0, max=60_000.0) / 1000.0,
            seed=node.integer("seed", d.seed, min=0, max=2 ** 63 - 1),
            schedule=schedule, progress=node.string("progress", d.progress, choices=EVOLUTION_PROGRESS),
            guided_model="" if guided is None else guided, guided_b=b, guided_W=W,
        )
        node.done()
        return out


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
    evolution: EvolutionSettings = field(default_factory=EvolutionSettings)  # used when refine == "evolution"

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
            evolution=EvolutionSettings.from_node(node.child("evolution", {})),
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
        evo = d.pop("evolution", None)  # absent in models saved before the evolution refinement
        if evo is None:
            return cls(**d, model=model)
        evo = {k: tuple(tuple(r) for r in v) if k == "guided_W" else tuple(v) if isinstance(v, list) else v
               for k, v in evo.items()}
        return cls(**d, model=model, evolution=EvolutionSettings(**evo))
