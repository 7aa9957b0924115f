"""Viewpoint-evolution pose refinement (Zhao et al., Appl. Sci. 2024, §2; docs/method.md).

A population of candidate camera poses evolves inside a feasible region that shrinks as
the population improves:

- **quality** `vp_q` (§2.1): per component (a planar face of the model, see
  `components.py`) the model points are projected with the candidate pose and matched to
  keypoints within the search radius `sigma`. A keypoint is a candidate for a model point
  only when that model point is one of its two nearest descriptors (the paper matches edge
  points; with SIFT a pure window search pairs random neighbours). Displacements are binned
  into slope ranges, each range's advantage is norm(count ratio) + 1 - norm(distance
  variance), and candidates are assigned in order of advantage, one-to-one. The matched
  ratio `cp_ra` goes through the paper's ISRU map (n_f = 5), the mean distance `cp_res` is
  normalised between the root pose's residual and a tenth of it, and the ridge function
  (two planes through (0,0)->0, (1,1)->1 and the measurement points vp_q0, vp_q1) gives
  the component's quality; `vp_q` is the mean over the components visible at the root.
- **feasible region** F_i (§2.2): poses whose mean squared reprojection error over each
  component's best correspondences so far is <= delta_i^2. Parents outside F are projected
  onto its boundary (SQP on the linearised constraint, nearest in pose distance); from
  there Huber-LM trajectories are recorded, and poses interpolated between neighbouring
  trajectories whose steps agree in direction complete the sparse approximation of F.
- **migration** (§2.3, eq. 14): a parent moves to a random point among the first
  (1 - lambda) of its trajectory.
- **offspring** (eqs. 15-17): basic directions are damped Gauss-Newton steps with the
  rotation or the translation clipped, chosen with the paper's probabilities (descending
  directions share 1 - p_e, the others p_e, softmax of the predicted decrease); each is
  perturbed in a cone of angle tau (rotation and translation separately), lengthened by
  s times the parent's trajectory length, and pulled a random fraction (0..alpha) toward
  the affine span of its three nearest points of F's approximation.
- **evolution functions** map the population quality to (delta, sigma, lambda, s, tau,
  alpha): linear between the paper's initial and final values over the quality range
  [vp_q(P_1), min(eps * vp_q(P_1), 1)] by default, or the paper's guided model (power laws
  with a correlation matrix, fitted from good runs: `fit_guided`).

Poses live in a chart around the root pose: x = (zbar * log(R R0^T), t - R R0^T t0), the
rotation scaled by the mean depth of the model points so that both halves are metres. The
paper's slerp interpolation becomes linear interpolation in this chart (equal to first
order for the small angles involved). Deterministic for a given `numpy.random.Generator`
unless the wall-time budget ends the run; then the best candidate so far is returned with
status BUDGET.
"""

from __future__ import annotations

import enum
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from supervisor.errors import ConfigError
from supervisor.localization.settings import EVOLUTION_PARAMS as PARAMS
from supervisor.localization.settings import EvolutionSettings

_NF = 5.0  # ISRU transformation factor of cp_ra (the paper's n_f)
_MIN_COMPONENT_POINTS = 3  # a component is visible at the root with at least this many matched points


class EvolutionStatus(enum.Enum):
    CONVERGED = "converged"  # the parents' mean quality reached the termination threshold
    STALLED = "stalled"  # no better candidate for `patience` rounds
    MAX_ROUNDS = "max_rounds"
    BUDGET = "budget"  # wall-time budget hit: the best candidate so far is returned
    NOT_RUN = "not_run"  # too few components or correspondences: the start pose is returned


@dataclass(frozen=True)
class GuidedModel:
    """The paper's guided model (eq. 20): normalised e = W^T (1 - x^b), x = normalised quality."""

    b: tuple[float, ...]  # one exponent per parameter (PARAMS order)
    W: tuple[tuple[float, ...], ...]  # 6x6 correlation matrix
    meta: dict[str, Any] = field(default_factory=dict, compare=False)

    def __post_init__(self) -> None:
        b, W = np.asarray(self.b, float), np.asarray(self.W, float)
        if b.shape != (len(PARAMS),) or W.shape != (len(PARAMS), len(PARAMS)):
            raise ValueError(f"guided model needs b of length {len(PARAMS)} and a {len(PARAMS)}x{len(PARAMS)} W")
        if not (np.all(np.isfinite(b)) and np.all(np.isfinite(W)) and np.all(b > 0)):
            raise ValueError("guided model: b must be positive and finite, W finite")

    def normalised(self, x: float) -> np.ndarray:
        phi = 1.0 - np.clip(x, 0.0, 1.0) ** np.asarray(self.b)
        return np.clip(phi @ np.asarray(self.W), 0.0, 1.0)

    def to_json(self) -> dict[str, Any]:
        return {"format": "viewpoint-evolution-guided-model", "version": 1, "params": list(PARAMS),
                "b": list(self.b), "W": [list(r) for r in self.W], "meta": self.meta}

    @classmethod
    def load(cls, path: str | Path) -> GuidedModel:
        path = Path(path)
        try:
            d = json.loads(path.read_text())
            if d.get("format") != "viewpoint-evolution-guided-model" or list(d.get("params", [])) != list(PARAMS):
                raise ValueError("not a guided-model file (format/params)")
            return cls(tuple(float(v) for v in d["b"]), tuple(tuple(float(v) for v in r) for r in d["W"]),
                       dict(d.get("meta", {})))
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise ConfigError(path, "", f"cannot read the guided evolution model: {exc}") from exc


@dataclass(frozen=True)
class Frame:
    """What the evolution sees of one frame: keypoints, their two nearest model descriptors, the model."""

    keypoints: np.ndarray  # (N, 2) px, undistorted
    knn_idx: np.ndarray  # (N, 2) model indices of each keypoint's two nearest descriptors
    points: np.ndarray  # (M, 3) model points, target frame, m
    labels: np.ndarray  # (M,) component of each model point, -1 none
    K: np.ndarray  # 3x3


@dataclass
class Node:
    """One evaluated candidate and the parameter values actually used to make it (for the guided fit)."""

    x: np.ndarray
    q: float
    parent: int  # index into the run's node list, -1 for the initial population
    round: int
    values: dict[str, float]  # normalised sampled values of PARAMS


@dataclass(frozen=True)
class EvolutionResult:
    T_cam_target: np.ndarray
    status: EvolutionStatus
    rounds: int
    quality: float  # vp_q of the returned pose
    quality_start: float  # vp_q of the start pose at the first radius
    evaluations: int
    elapsed: float  # s
    nodes: list[Node] = field(default_factory=list, repr=False)
    best_node: int = -1
    progress: list[float] = field(default_factory=list, repr=False)  # normalised population quality per round


# -- small SO(3) helpers, vectorised ------------------------------------------------------

def _hat(w: np.ndarray) -> np.ndarray:
    z = np.zeros(w.shape[:-1])
    return np.stack([np.stack([z, -w[..., 2], w[..., 1]], -1), np.stack([w[..., 2], z, -w[..., 0]], -1),
                     np.stack([-w[..., 1], w[..., 0], z], -1)], -2)


def _exp(w: np.ndarray) -> np.ndarray:
    th = np.linalg.norm(w, axis=-1)[..., None, None]
    W = _hat(w)
    small = th < 1e-9
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0, np.sin(ths) / ths)
    b = np.where(small, 0.5, (1 - np.cos(ths)) / ths ** 2)
    return np.eye(3) + a * W + b * (W @ W)


def _log(R: np.ndarray) -> np.ndarray:
    c = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1) / 2, -1.0, 1.0)
    th = np.arccos(c)
    v = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    s = np.sin(th)
    f = np.where(th < 1e-9, 0.5, th / (2 * np.where(th < 1e-9, 1.0, s)))
    return f[..., None] * v


class _Chart:
    """Poses as 6-vectors about the root pose, rotation scaled by the mean depth (metres throughout)."""

    def __init__(self, T0: np.ndarray, zbar: float) -> None:
        self.R0, self.t0, self.z = T0[:3, :3], T0[:3, 3], zbar

    def pose(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        R = _exp(x[..., :3] / self.z) @ self.R0
        t = (R @ self.R0.T @ self.t0[:, None])[..., 0] + x[..., 3:]
        return R, t

    def coords(self, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        Rd = R @ self.R0.T
        return np.concatenate([_log(Rd) * self.z, t - (Rd @ self.t0[:, None])[..., 0]], -1)

    def compose(self, delta: np.ndarray, x: np.ndarray) -> np.ndarray:
        """Coordinates of Exp(delta) * T(x) (a left increment in camera coordinates, scaled like x)."""
        R, t = self.pose(x)
        D = _exp(delta[..., :3] / self.z)
        return self.coords(D @ R, (D @ t[..., None])[..., 0] + delta[..., 3:])

    def T(self, x: np.ndarray) -> np.ndarray:
        R, t = self.pose(x)
        out = np.eye(4)
        out[:3, :3], out[:3, 3] = R, t
        return out


# -- the evolution ------------------------------------------------------------------------

class _Run:
    def __init__(self, frame: Frame, T0: np.ndarray, s: EvolutionSettings, rng: np.random.Generator,
                 clock: Callable[[], float]) -> None:
        self.f, self.s, self.rng, self.clock = frame, s, rng, clock
        self.t_start = clock()
        P = frame.points
        zs = P @ T0[2, :3] + T0[2, 3]
        self.chart = _Chart(T0, float(np.median(zs)) if np.any(zs > 0) else 1.0)
        fx, fy, cx, cy = frame.K[0, 0], frame.K[1, 1], frame.K[0, 2], frame.K[1, 2]
        self.kf = (fx, fy, cx, cy)
        # Candidate pairs (keypoint, model point): each keypoint with its two nearest model descriptors,
        # restricted to points that belong to a component.
        k = np.repeat(np.arange(len(frame.keypoints)), 2)
        m = frame.knn_idx.reshape(-1)
        ok = (m >= 0) & (m < len(P))
        k, m = k[ok], m[ok]
        lab = frame.labels[m]
        keep = lab >= 0
        self.pk, self.pm, self.pw = k[keep], m[keep], lab[keep]
        self.n_comp = int(frame.labels.max()) + 1 if len(frame.labels) else 0
        self.nodes: list[Node] = []
        self.evaluations = 0
        lo, hi = P.min(axis=0), P.max(axis=0)
        self.extremes = np.array([[(lo, hi)[i >> k & 1][k] for k in range(3)] for i in range(8)])
        x0 = np.zeros((1, 6))
        self.extremes_root = self._project(x0, self.extremes)[0][0]
        uv0 = self._project(x0, P[self.pm])[0][0]
        self.root_dist = np.hypot(*(frame.keypoints[self.pk] - uv0).T)

    # -- quality ---------------------------------------------------------------------------
    def _project(self, x: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        R, t = self.chart.pose(x)
        Y = np.einsum("cij,pj->cpi", R.reshape(-1, 3, 3), P) + t.reshape(-1, 1, 3)
        fx, fy, cx, cy = self.kf
        z = Y[..., 2]
        zs = np.where(z > 1e-6, z, 1e-6)
        return np.stack([fx * Y[..., 0] / zs + cx, fy * Y[..., 1] / zs + cy], -1), z

    def assign(self, X: np.ndarray, sigma: float) -> tuple[np.ndarray, ...]:
        """Matched pairs per candidate after the direction-advantage assignment:
        (candidate, pair index, distance) arrays, one entry per matched model point."""
        # Only pairs that some candidate can bring within sigma: within sigma + (the candidates' largest
        # image displacement of the model's extreme points) of their projection under the root pose.
        ext, _ = self._project(X, self.extremes)
        shift = float(np.max(np.hypot(*(ext - self.extremes_root[None]).transpose(2, 0, 1))))
        near = np.flatnonzero(self.root_dist <= sigma + shift)
        uv, z = self._project(X, self.f.points[self.pm[near]])
        d = self.f.keypoints[self.pk[near]][None] - uv
        dist = np.hypot(d[..., 0], d[..., 1])
        c, jn = np.nonzero((z > 1e-6) & (dist <= sigma))
        j = near[jn]
        d = d[c, jn]
        dist = dist[c, jn]
        if len(c) == 0:
            return c, j, np.empty(0)
        dd = dist
        S = self.s.sectors
        sec = (np.floor((np.arctan2(d[:, 1], d[:, 0]) + np.pi) / (2 * np.pi / S)).astype(int)) % S
        w = self.pw[j]
        C, Wn = len(X), max(self.n_comp, 1)
        cw = c * Wn + w
        g = cw * S + sec  # (candidate, component, sector) group
        ng = C * Wn * S
        cnt = np.bincount(g, minlength=ng).astype(float)
        s1 = np.bincount(g, dd, ng)
        s2 = np.bincount(g, dd * dd, ng)
        tot = np.bincount(cw, minlength=C * Wn).astype(float)
        cnt3 = cnt.reshape(-1, S)
        with np.errstate(invalid="ignore", divide="ignore"):
            ra = cnt3 / np.maximum(tot[:, None], 1)
            mean = s1.reshape(-1, S) / np.maximum(cnt3, 1)
            var = s2.reshape(-1, S) / np.maximum(cnt3, 1) - mean ** 2
        present = cnt3 > 0

        def norm(a: np.ndarray) -> np.ndarray:
            lo = np.where(present, a, np.inf).min(axis=1, keepdims=True)
            hi = np.where(present, a, -np.inf).max(axis=1, keepdims=True)
            span = hi - lo
            return np.where(span > 1e-12, (a - lo) / np.where(span > 1e-12, span, 1.0), 1.0)

        adv = (norm(ra) + 1.0 - norm(var)).reshape(-1)[g]
        # One candidate per model point (best advantage, then nearest), then one model point per keypoint.
        order = np.lexsort((dd, -adv, self.pm[j], c))
        keym = c[order] * len(self.f.points) + self.pm[j[order]]
        first = np.ones(len(order), bool)
        first[1:] = keym[1:] != keym[:-1]
        sel = order[first]
        order2 = sel[np.lexsort((dd[sel], -adv[sel], self.pk[j[sel]], c[sel]))]
        keyk = c[order2] * len(self.f.keypoints) + self.pk[j[order2]]
        first = np.ones(len(order2), bool)
        first[1:] = keyk[1:] != keyk[:-1]
        sel = order2[first]
        return c[sel], j[sel], dd[sel]

    def component_stats(self, X: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, ...]]:
        """(cp_ra, cp_res) per candidate and component, and the matches behind them."""
        c, j, dd = self.assign(X, sigma)
        C, Wn = len(X), max(self.n_comp, 1)
        cw = c * Wn + self.pw[j]
        n = np.bincount(cw, minlength=C * Wn).reshape(C, Wn).astype(float)
        res = np.bincount(cw, dd, C * Wn).reshape(C, Wn)
        with np.errstate(invalid="ignore", divide="ignore"):
            cp_res = np.where(n > 0, res / np.maximum(n, 1), np.nan)
        cp_ra = n / np.maximum(self.n_visible_points[None], 1)
        return np.clip(cp_ra, 0.0, 1.0), cp_res, (c, j, dd)

    def quality(self, cp_ra: np.ndarray, cp_res: np.ndarray) -> np.ndarray:
        """Per candidate and visible component: ISRU(cp_ra) and the ridge function (eqs. 2-3)."""
        a = 2 * _NF * cp_ra - _NF
        ra = np.clip(0.5 * (1.07 * a / np.sqrt(1.5 + a * a) + 1.0), 0.0, 1.0)
        root, ideal = self.root_res[None], 0.1 * self.root_res[None]
        with np.errstate(invalid="ignore", divide="ignore"):
            u = np.clip((cp_res - root) / (ideal - root), 0.0, 1.0)
        u = np.where(np.isfinite(u), u, 0.0)
        q0, q1 = self.s.vpq
        q = np.where(ra <= u, q0 * u + (1 - q0) * ra, (1 - q1) * u + q1 * ra)
        q = np.where(np.isfinite(cp_res), q, 0.0)
        return q[:, self.visible]

    def evaluate(self, X: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, ...]]:
        cp_ra, cp_res, m = self.component_stats(X, sigma)
        qw = self.quality(cp_ra, cp_res)
        self.evaluations += len(X)
        return qw.mean(axis=1), qw, m

    # -- feasible region ------------------------------------------------------------------
    def residuals(self, x: np.ndarray, m_idx: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Reprojection residuals (..., n, 2) and their Jacobian (..., n, 2, 6) w.r.t. a left increment
        (chart units), for one pose (6,) or a batch (B, 6)."""
        R, t = self.chart.pose(x)
        Y = np.einsum("...ij,nj->...ni", R, self.f.points[m_idx]) + t[..., None, :]
        fx, fy, cx, cy = self.kf
        z = np.maximum(Y[..., 2], 1e-6)
        xz, yz = Y[..., 0] / z, Y[..., 1] / z
        r = np.stack([fx * xz + cx, fy * yz + cy], -1) - uv
        iz = 1.0 / z
        X_, Y_, Z_ = Y[..., 0], Y[..., 1], Y[..., 2]
        zero = np.zeros_like(z)
        # d(pi)/dY times dY/d(omega) = -[Y]x (omega in chart units: / zbar), and dY/dv = I
        du = np.stack([fx * iz, zero, -fx * xz * iz], -1)
        dv = np.stack([zero, fy * iz, -fy * yz * iz], -1)
        Yv = np.stack([X_, Y_, Z_], -1)
        J = np.stack([np.concatenate([np.cross(Yv, du) / self.chart.z, du], -1),
                      np.concatenate([np.cross(Yv, dv) / self.chart.z, dv], -1)], -2)
        return r, J

    def project_to_boundary(self, x: np.ndarray, corr: tuple[np.ndarray, np.ndarray], delta: float) -> np.ndarray:
        """SQP (eqs. 6-9): the pose nearest x with mean squared error = delta^2; x itself if inside F."""
        n = len(corr[0])
        xk = x.copy()
        for _ in range(4):
            r, J = self.residuals(xk, *corr)
            g = float(np.sum(r * r)) / n - delta * delta
            if g <= 0 and np.array_equal(xk, x):
                return x  # already feasible
            grad = 2.0 / n * np.einsum("ni,nij->j", r, J)
            gg = float(grad @ grad)
            if gg < 1e-18:
                break
            dx = x - xk
            step = dx - grad * (grad @ dx + g) / gg
            xk = self.chart.compose(step, xk)
            if abs(g) < 1e-3 * delta * delta:
                break
        return xk

    def trajectories(self, X: np.ndarray, corr: tuple[np.ndarray, np.ndarray]) -> list[list[np.ndarray]]:
        """Huber-LM from every row of X on the best correspondences (eq. 10), solved as one batch;
        every accepted pose of each run is recorded (its trajectory)."""
        hub = self.s.huber_px

        def cost(r: np.ndarray) -> np.ndarray:
            e = np.hypot(r[..., 0], r[..., 1])
            return np.sum(np.where(e <= hub, 0.5 * e * e, hub * (e - 0.5 * hub)), axis=-1)

        B = len(X)
        trajs = [[X[i]] for i in range(B)]
        x = X.copy()
        lam = np.full(B, 1e-3)
        active = np.ones(B, bool)
        r, J = self.residuals(x, *corr)
        c = cost(r)
        for _ in range(self.s.lm_iterations):
            if not active.any():
                break
            e = np.hypot(r[..., 0], r[..., 1])
            w = np.where(e <= hub, 1.0, hub / np.maximum(e, 1e-12))
            Jf = J.reshape(B, -1, 6)
            Jw = Jf * np.repeat(w, 2, axis=1)[..., None]
            H = Jw.transpose(0, 2, 1) @ Jf
            g = (Jw.transpose(0, 2, 1) @ r.reshape(B, -1, 1))[..., 0]
            accepted = np.zeros(B, bool)
            for _retry in range(4):
                todo = active & ~accepted
                if not todo.any():
                    break
                D = H[todo] + lam[todo, None, None] * (np.eye(6) * (np.diagonal(H[todo], axis1=1, axis2=2)[:, None]
                                                                   + 1e-12))
                step = -np.linalg.solve(D, g[todo][..., None])[..., 0]
                xn = self.chart.compose(step, x[todo])
                rn, Jn = self.residuals(xn, *corr)
                cn = cost(rn)
                better = cn < c[todo]
                idx = np.flatnonzero(todo)
                for k, i in enumerate(idx):
                    if better[k]:
                        x[i], r[i], J[i], c[i] = xn[k], rn[k], Jn[k], cn[k]
                        trajs[i].append(xn[k])
                        accepted[i] = True
                        lam[i] = max(lam[i] / 10, 1e-7)
                        if np.linalg.norm(step[k]) < 1e-8:
                            active[i] = False
                    else:
                        lam[i] *= 10
            active &= accepted
        return trajs

    @staticmethod
    def interpolate(trajs: list[list[np.ndarray]]) -> list[np.ndarray]:
        """Poses between neighbouring trajectories whose steps agree in direction (eqs. 11-13)."""
        out = []
        for z in range(max((len(t) for t in trajs), default=0) - 1):
            for m in range(len(trajs) - 1):
                a, b = trajs[m], trajs[m + 1]
                if len(a) <= z + 1 or len(b) <= z + 1:
                    continue
                da, db = a[z + 1] - a[z], b[z + 1] - b[z]
                na, nb, gap = np.linalg.norm(da), np.linalg.norm(db), np.linalg.norm(b[z] - a[z])
                if na < 1e-12 or nb < 1e-12 or gap < 1e-12 or da @ db <= 0:
                    continue
                t = min((na + nb) / (2 * gap), 1.0)
                out.append(a[z] + t * (b[z] - a[z]))
        return out


def _schedule(s: EvolutionSettings, x: float, delta0: float) -> dict[str, float]:
    """Evolution-function values at normalised population quality x in [0, 1]."""
    if s.schedule == "linear":
        e = (1.0 - np.clip(x, 0.0, 1.0)) * np.ones(len(PARAMS))
    else:
        e = GuidedModel(s.guided_b, s.guided_W).normalised(x)
    ranges = {"delta": (delta0, 0.0), **s.initial_final()}
    return {p: ranges[p][1] + float(e[i]) * (ranges[p][0] - ranges[p][1]) for i, p in enumerate(PARAMS)}


def _normalised(s: EvolutionSettings, p: str, v: float, delta0: float) -> float:
    a, b = {"delta": (delta0, 0.0), **s.initial_final()}[p]
    return float((v - b) / (a - b)) if a != b else 0.0


def _cone(d: np.ndarray, tau: float, rng: np.random.Generator) -> np.ndarray:
    """A direction within angle tau of d (same length); d = 0 stays 0."""
    n = np.linalg.norm(d)
    if n < 1e-15 or tau <= 0:
        return d.copy()
    u = d / n
    r = rng.standard_normal(3)
    perp = r - (r @ u) * u
    pn = np.linalg.norm(perp)
    if pn < 1e-12:
        return d.copy()
    ang = rng.uniform(0.0, tau)
    return n * (math.cos(ang) * u + math.sin(ang) * perp / pn)


def evolve(frame: Frame, T_start: np.ndarray, settings: EvolutionSettings, rng: np.random.Generator,
           clock: Callable[[], float] = time.perf_counter, record: bool = False) -> EvolutionResult:
    """Refine `T_start` (T_cam_target) by viewpoint evolution; see the module docstring."""
    s = settings
    run = _Run(frame, np.asarray(T_start, float), s, rng, clock)
    x0 = np.zeros(6)

    def result(x: np.ndarray, status: EvolutionStatus, rounds: int, q: float, q_start: float, best: int = -1,
               progress: list[float] | None = None) -> EvolutionResult:
        return EvolutionResult(run.chart.T(x), status, rounds, q, q_start, run.evaluations, clock() - run.t_start,
                               run.nodes if record else [], best, progress or [])

    sigma0 = s.sigma_range[0]
    # Root: visible components and their residuals (the ridge function's reference).
    run.n_visible_points = _points_per_component(run)
    run.visible = np.ones(run.n_comp, bool)
    run.root_res = np.ones(run.n_comp)
    if run.n_comp == 0:
        return result(x0, EvolutionStatus.NOT_RUN, 0, math.nan, math.nan)
    cp_ra, cp_res, _ = run.component_stats(x0[None], sigma0)
    counts = cp_ra[0] * np.maximum(run.n_visible_points, 1)
    run.visible = np.isfinite(cp_res[0]) & (counts >= _MIN_COMPONENT_POINTS)
    if not run.visible.any():
        return result(x0, EvolutionStatus.NOT_RUN, 0, math.nan, math.nan)
    run.root_res = np.where(np.isfinite(cp_res[0]), np.maximum(cp_res[0], 1e-3), 1.0)

    # Initial population: the start pose and P-1 poses sampled in an ellipsoid about it.
    P, C = s.parents, s.children
    z = run.chart.z
    X = np.zeros((P, 6))
    for i in range(1, P):
        g = rng.standard_normal(6)
        g /= np.linalg.norm(g)
        X[i] = g * rng.uniform() ** (1 / 6) * np.r_[[s.init_rotation * z] * 3, [s.init_translation] * 3]
    q, qw, m = run.evaluate(X, sigma0)
    for i in range(P):
        run.nodes.append(Node(X[i], float(q[i]), -1, 0, {}))
    ids = list(range(P))
    q_start = float(q[0])
    q_head = float(q.mean())
    q_tail = min(s.termination * q_head, 1.0) if q_head > 0 else 1.0
    # Each visible component's best quality and correspondences so far.
    best_qw = np.full(run.n_comp, -np.inf)
    best_corr: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def update_components(qw: np.ndarray, m: tuple[np.ndarray, ...]) -> None:
        """Reset a component's best (quality and correspondences x_w) when a candidate beats it."""
        c, j, _ = m
        for col, w in enumerate(np.flatnonzero(run.visible)):
            k = int(np.argmax(qw[:, col]))
            if qw[k, col] > best_qw[w] + 1e-12:
                best_qw[w] = qw[k, col]
                sel = (c == k) & (run.pw[j] == w)
                best_corr[w] = (run.pm[j[sel]], frame.keypoints[run.pk[j[sel]]])

    update_components(qw, m)
    # delta_0: the mean cp_res of the first parents (the paper's reference)
    delta0 = float(np.nanmean(run.component_stats(X, sigma0)[1][:, run.visible]))
    best_i = int(np.argmax(q))
    best = (X[best_i].copy(), float(q[best_i]), ids[best_i])
    progress: list[float] = []
    stale = 0
    rounds = 0
    status = EvolutionStatus.MAX_ROUNDS
    budget = s.budget

    def over_budget() -> bool:
        return budget > 0 and clock() - run.t_start > budget

    def progress_of(qv: float, rnd: int) -> float:
        """Normalised quality progress: the evolution functions' abscissa (and, with
        progress: quality_or_rounds, at least the fraction of rounds done)."""
        x = (qv - q_head) / (q_tail - q_head) if q_tail > q_head else 1.0
        return max(x, (rnd - 1) / max(s.max_rounds - 1, 1)) if s.progress == "quality_or_rounds" else x

    for rnd in range(1, s.max_rounds + 1):
        xq = progress_of(float(q.mean()), rnd)
        progress.append(xq)
        if q.mean() >= q_tail - 1e-9:
            status = EvolutionStatus.CONVERGED
            break
        if over_budget():
            status = EvolutionStatus.BUDGET
            break
        par = _schedule(s, xq, delta0)
        corr_w = [best_corr[w] for w in sorted(best_corr)]
        corr = (np.concatenate([a for a, _ in corr_w]), np.concatenate([b for _, b in corr_w]))
        if len(corr[0]) < 6:
            status = EvolutionStatus.NOT_RUN
            break
        # Feasible region F_i: boundary projection of the parents, LM trajectories, interpolation.
        r_best, _ = run.residuals(best[0], *corr)
        delta = max(par["delta"], 1.05 * math.sqrt(float(np.mean(np.sum(r_best ** 2, axis=1)))))
        trajs = run.trajectories(np.array([run.project_to_boundary(X[i], corr, delta) for i in range(P)]), corr)
        rmin = float(np.min(np.mean(np.sum(run.residuals(np.array([t[-1] for t in trajs]), *corr)[0] ** 2, -1),
                                    -1)))
        delta = max(par["delta"], 1.05 * math.sqrt(rmin))
        F = np.array([p for t in trajs for p in t] + run.interpolate(trajs))
        # Migration (eq. 14), each parent's lambda from its own quality.
        Xm = np.empty_like(X)
        mig_frac = np.empty(P)
        for i in range(P):
            lam = _schedule(s, progress_of(float(q[i]), rnd), delta0)["lambda"]
            V = len(trajs[i]) - 1
            jmax = int(math.floor((1.0 - lam) * V))
            jj = int(rng.integers(0, jmax + 1))
            Xm[i] = trajs[i][jj]
            mig_frac[i] = 1.0 - jj / V if V > 0 else lam
        if over_budget():
            X, status = Xm, EvolutionStatus.BUDGET
            break
        # Offspring (eqs. 15-17).
        kids, kid_parent, kid_vals = [], [], []
        for i in range(P):
            pi = _schedule(s, progress_of(float(q[i]), rnd), delta0)
            r, J = run.residuals(Xm[i], *corr)
            Jf, rf = J.reshape(-1, 6), r.reshape(-1)
            length = sum(float(np.linalg.norm(trajs[i][k + 1] - trajs[i][k])) for k in range(len(trajs[i]) - 1))
            dirs, gains = [], []
            for keep in (np.r_[True, True, True, False, False, False], np.r_[False, False, False, True, True, True]):
                Jo = Jf * keep
                H = Jo.T @ Jo
                g = Jo.T @ rf
                trust = 1e-6 * max(float(np.trace(H)), 1e-12)
                d = -np.linalg.solve(H + trust * np.eye(6), g) * keep
                dirs.append(d)
                gains.append(float(-d @ g - 0.5 * d @ H @ d))
            gains_a = np.array(gains)
            scale = max(float(np.max(np.abs(gains_a))), 1e-12)
            e = np.exp(gains_a / scale)
            pos = gains_a > 0
            p_o = np.zeros(len(dirs))
            if pos.all() or not pos.any():
                p_o = e / e.sum()
            else:
                p_o[pos] = (1 - s.explore_probability) * e[pos] / e[pos].sum()
                p_o[~pos] = s.explore_probability * e[~pos] / e[~pos].sum()
            for _ in range(C):
                o = int(rng.choice(len(dirs), p=p_o))
                d = dirs[o]
                dp = np.concatenate([_cone(d[:3], pi["tau"], rng), _cone(d[3:], pi["tau"], rng)])
                nd = np.linalg.norm(dp)
                if nd > 1e-15:
                    dp = dp * (1.0 + pi["scale"] * length / nd)
                cpre = run.chart.compose(dp, Xm[i])
                a = float(rng.uniform(0.0, pi["alpha"])) if pi["alpha"] > 0 else 0.0
                if len(F) >= 3 and a > 0:
                    near = F[np.argsort(np.linalg.norm(F - cpre, axis=1))[:3]]
                    A = (near[1:] - near[0]).T
                    coef, *_ = np.linalg.lstsq(A, cpre - near[0], rcond=None)
                    cpre = cpre + a * (near[0] + A @ coef - cpre)
                kids.append(cpre)
                kid_parent.append(i)
                angle = _angle(dp[:3], d[:3]) if np.linalg.norm(d[:3]) > 0 else _angle(dp[3:], d[3:])
                kid_vals.append({"delta": _normalised(s, "delta", delta, delta0),
                                 "sigma": _normalised(s, "sigma", par["sigma"], delta0),
                                 "lambda": _normalised(s, "lambda", mig_frac[i], delta0),
                                 "scale": _normalised(s, "scale", pi["scale"], delta0),
                                 "tau": _normalised(s, "tau", angle, delta0),
                                 "alpha": _normalised(s, "alpha", a, delta0)})
        # Selection from {C_i, P_i'} (the migrated parents and the best so far are re-scored at this radius).
        pool = np.vstack([Xm, np.array(kids), best[0][None]])
        qp, qwp, mp = run.evaluate(pool, par["sigma"])
        rounds = rnd
        base = len(run.nodes)
        pool_ids = []
        for i in range(P):
            run.nodes.append(Node(Xm[i], float(qp[i]), ids[i], rnd, {}))
            pool_ids.append(base + i)
        for k, x in enumerate(kids):
            run.nodes.append(Node(x, float(qp[P + k]), pool_ids[kid_parent[k]], rnd, kid_vals[k]))
            pool_ids.append(base + P + k)
        pool_ids.append(best[2])
        # A reset of a component's best by a child triggers the region update (next round's corr).
        nk = len(kids)
        update_components(qwp[P:P + nk], _shift(mp, P, nk))
        order = np.argsort(-qp, kind="stable")
        chosen = []
        seen: set[int] = set()
        for k in order:
            key = pool_ids[k]
            if key in seen:
                continue
            seen.add(key)
            chosen.append(int(k))
            if len(chosen) == P:
                break
        X, q, ids = pool[chosen], qp[chosen], [pool_ids[k] for k in chosen]
        top = int(order[0])
        if qp[top] > float(qp[-1]) + 1e-12:  # a candidate beat the best so far (re-scored at this radius)
            best = (pool[top].copy(), float(qp[top]), pool_ids[top])
            stale = 0
        else:
            best = (best[0], float(qp[-1]), best[2])
            stale += 1
            if stale >= s.patience:
                status = EvolutionStatus.STALLED
                break
    return result(best[0], status, rounds, best[1], q_start, best[2], progress)


def _points_per_component(run: _Run) -> np.ndarray:
    """Model points per component that are a 2-NN of some keypoint (the points that can be matched)."""
    if run.n_comp == 0:
        return np.zeros(0)
    um = np.unique(run.pm)
    return np.bincount(run.f.labels[um], minlength=run.n_comp).astype(float)


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    return float(np.arccos(np.clip(a @ b / (na * nb), -1.0, 1.0))) if na > 0 and nb > 0 else 0.0


def _shift(m: tuple[np.ndarray, ...], start: int, n: int) -> tuple[np.ndarray, ...]:
    """Matches of candidates start..start+n-1, renumbered from 0."""
    c, j, dd = m
    sel = (c >= start) & (c < start + n)
    return c[sel] - start, j[sel], dd[sel]


# -- the guided model (§2.4) ------------------------------------------------------------------

def guided_samples(result: EvolutionResult) -> tuple[np.ndarray, np.ndarray]:
    """(x, e): the normalised population progress and the normalised sampled parameter values along the
    lineage of a run's returned candidate (run with `record=True`): the paper's trajectory T of a good run."""
    xs, es = [], []
    k = result.best_node
    while 0 <= k < len(result.nodes):
        node = result.nodes[k]
        if node.values and 1 <= node.round <= len(result.progress):
            xs.append(result.progress[node.round - 1])
            es.append([node.values[p] for p in PARAMS])
        k = node.parent
    return np.array(xs, float).reshape(-1), np.array(es, float).reshape(-1, len(PARAMS))


def b_level(i: int, b0: float = 1.5, p_r: float = 0.5) -> float:
    """The exponent of guidance level i (the paper's decreasing-integral rule, eqs. 21-22), for
    e(b) = 1 - x^b: integral(e(b_i)) = integral(e(b_0)) - i p_r (integral(e(1)) - integral(e(b_0)))."""
    integral = lambda b: b / (b + 1.0)  # noqa: E731
    target = integral(b0) - i * p_r * (integral(1.0) - integral(b0))
    if not 0.0 < target < 1.0:
        raise ValueError(f"guidance level {i} has no exponent (integral {target:g})")
    return target / (1.0 - target)


def fit_guided(x: np.ndarray, e: np.ndarray, b0: float = 1.5, p_r: float = 0.5) -> GuidedModel:
    """Fit the guided model e ~ W^T (1 - x^b) (eq. 20) to samples from good runs, starting from b = b0, W = I."""
    from scipy.optimize import least_squares

    x = np.clip(np.asarray(x, float), 0.0, 1.0)
    e = np.asarray(e, float)
    n = len(PARAMS)
    if len(x) < 2 * n or e.shape != (len(x), n):
        raise ValueError(f"guided fit needs at least {2 * n} samples of {n} values, got {e.shape}")

    def resid(theta: np.ndarray) -> np.ndarray:
        b, W = theta[:n], theta[n:].reshape(n, n)
        return ((1.0 - x[:, None] ** b[None]) @ W - e).ravel()

    theta0 = np.concatenate([np.full(n, b0), np.eye(n).ravel()])
    lo = np.concatenate([np.full(n, 0.1), np.full(n * n, -5.0)])
    hi = np.concatenate([np.full(n, 20.0), np.full(n * n, 5.0)])
    sol = least_squares(resid, theta0, bounds=(lo, hi), max_nfev=2000)
    b, W = sol.x[:n], sol.x[n:].reshape(n, n)
    meta = {"samples": int(len(x)), "rms": float(np.sqrt(np.mean(sol.fun ** 2))), "b0": b0, "p_r": p_r,
            "next_level_b": b_level(1, b0, p_r)}
    return GuidedModel(tuple(float(v) for v in b), tuple(tuple(float(v) for v in r) for r in W), meta)
