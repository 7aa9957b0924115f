"""What every predictor shares: the prediction it returns, the samples it keeps, and its protocol.

`predictors.py` (the EMG-based predictors and the static envelope) and `mlp.py`
(the paper's MLP baseline) both build on this module and not on each other.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np


@dataclass(frozen=True)
class Prediction:
    valid: bool
    boundary: float  # SI; nan when not valid
    allow_next: bool | None  # next-step rule (None: the predictor has no opinion)
    reason: str
    x_now: float  # SI, the furthest sampled position
    fit: object | None = None  # FitResult (params in fit units) when there is one
    params: tuple[float, float, float] | None = None  # (alpha, K, mu) in fit units, for plots
    scale: float = 1.0  # EMG width in fit units (1 = the paper's model): curve = emg(x, *params, scale)
    # which boundary binds: "" (the n_i model) or "error_bound" (the error-aware boundary is the
    # earlier one, or refuses a step the n_i model alone would allow)
    limited_by: str = ""


@dataclass
class _Samples:
    xs: list[float] = field(default_factory=list)  # SI
    ns: list[float] = field(default_factory=list)
    steps: int = 0

    def add(self, xs: np.ndarray, ns: np.ndarray) -> None:
        xs = np.asarray(xs, float).ravel()
        ns = np.asarray(ns, float).ravel()
        if xs.shape != ns.shape:
            raise ValueError(f"xs and ns differ in length ({len(xs)} vs {len(ns)})")
        self.xs.extend(xs.tolist())
        self.ns.extend(ns.tolist())
        self.steps += 1

    @property
    def x_now(self) -> float:
        return max(self.xs) if self.xs else 0.0



class Predictor(Protocol):
    """Samples in, prediction out: `update` takes one sampling step's frames (SI positions, inlier counts).

    A predictor that also models the pose uncertainty sets `needs_err = True`: the loop then calls
    `update(xs, ns, err=...)` with the step's per-frame (sd_t m, sd_r rad), nan where a frame did
    not localize."""

    kind: str

    def update(self, xs: np.ndarray, ns: np.ndarray) -> Prediction: ...

    def reset(self) -> None: ...
