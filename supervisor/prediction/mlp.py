"""The paper's MLP baseline: 3 hidden layers x 10 tanh units, x -> n_i.

Pre-trained on the EMG curve of the least-squares initial guess, then
fine-tuned on the samples plus artificial points at (x_max, 0) (the paper uses
(45 deg, 0)). Trained with L-BFGS on an analytic gradient (numpy + scipy; no
deep-learning framework needed for 261 weights). Deterministic given `seed`.
The boundary is where the network's output falls to n_t, searched on a fine
grid beyond its peak (next-step rule as for the EMG predictors).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import minimize

from supervisor.prediction.emg import ANGLE, Axis, emg, initial_guesses
from supervisor.prediction.base import Prediction, _Samples

_SIZES = (1, 10, 10, 10, 1)
_N_ARTIFICIAL = 5


class MLP:
    """A tiny fully-connected tanh network with a flat parameter vector."""

    def __init__(self, seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        parts = []
        for a, b in zip(_SIZES[:-1], _SIZES[1:]):
            parts.append(rng.normal(0.0, 1.0 / math.sqrt(a), (a, b)).ravel())
            parts.append(np.zeros(b))
        self.w = np.concatenate(parts)

    def _unpack(self, w: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        out, i = [], 0
        for a, b in zip(_SIZES[:-1], _SIZES[1:]):
            W = w[i:i + a * b].reshape(a, b)
            i += a * b
            out.append((W, w[i:i + b]))
            i += b
        return out

    def forward(self, x: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
        h = np.asarray(x, float).reshape(-1, 1)
        layers = self._unpack(self.w if w is None else w)
        for k, (W, b) in enumerate(layers):
            h = h @ W + b
            if k < len(layers) - 1:
                h = np.tanh(h)
        return h.ravel()

    def _loss_grad(self, w: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[float, np.ndarray]:
        layers = self._unpack(w)
        acts = [x.reshape(-1, 1)]
        h = acts[0]
        for k, (W, b) in enumerate(layers):
            h = h @ W + b
            if k < len(layers) - 1:
                h = np.tanh(h)
            acts.append(h)
        r = acts[-1].ravel() - y
        loss = float(np.mean(r * r))
        g = (2.0 / len(y)) * r.reshape(-1, 1)
        grads = []
        for k in range(len(layers) - 1, -1, -1):
            W, _ = layers[k]
            grads.append((acts[k].T @ g, g.sum(axis=0)))
            if k > 0:
                g = (g @ W.T) * (1.0 - acts[k] ** 2)
        flat = np.concatenate([np.concatenate([gw.ravel(), gb]) for gw, gb in reversed(grads)])
        return loss, flat

    def train(self, x: np.ndarray, y: np.ndarray, max_iter: int = 300) -> float:
        res = minimize(self._loss_grad, self.w, args=(np.asarray(x, float), np.asarray(y, float)), jac=True,
                       method="L-BFGS-B", options={"maxiter": max_iter})
        if np.all(np.isfinite(res.x)):
            self.w = res.x
        return float(res.fun)


class MLPPredictor:
    """The MLP baseline with the next-step rule."""

    kind = "mlp"

    def __init__(self, n_t: float, step: float, axis: Axis = ANGLE, x_max: float = math.radians(45.0),
                 seed: int = 0) -> None:
        self.n_t, self.step, self.axis, self.x_max, self.seed = float(n_t), float(step), axis, float(x_max), seed
        self.samples = _Samples()
        self.last: Prediction | None = None

    def reset(self) -> None:
        self.samples = _Samples()
        self.last = None

    def update(self, xs: np.ndarray, ns: np.ndarray, err: np.ndarray | None = None) -> Prediction:
        self.samples.add(xs, ns)
        self.last = self.predict_from(np.array(self.samples.xs), np.array(self.samples.ns))
        return self.last

    def fit_curve(self, x_si: np.ndarray, n: np.ndarray) -> tuple[MLP, float, float] | None:
        """Train on samples; returns (net, x scale, n scale) in fit units, or None for unusable data."""
        x = self.axis.to_fit(x_si)
        x_max = float(self.axis.to_fit(self.x_max))
        if len(x) < 3 or len(np.unique(x)) < 2 or not (np.all(np.isfinite(x)) and np.all(np.isfinite(n))) \
                or np.ptp(n) == 0:
            return None
        n_scale = float(max(np.max(n), 1.0))
        net = MLP(self.seed)
        grid = np.linspace(0.0, x_max, 60)
        net.train(grid / x_max, emg(grid, *initial_guesses(x, n)[0]) / n_scale, max_iter=200)  # pre-training
        xa = np.concatenate([x, np.full(_N_ARTIFICIAL, x_max)])
        ya = np.concatenate([n, np.zeros(_N_ARTIFICIAL)])
        net.train(xa / x_max, ya / n_scale, max_iter=300)  # fine-tuning
        return net, x_max, n_scale

    def boundary_of(self, curve: tuple[MLP, float, float], n_t: float, x_now_si: float) -> float:
        net, x_max, n_scale = curve
        x_now = float(self.axis.to_fit(x_now_si))
        grid = np.arange(0.0, x_max + 1e-9, 0.05)
        y = net.forward(grid / x_max) * n_scale
        i_pk = int(np.argmax(y))
        start = max(i_pk, int(np.searchsorted(grid, x_now)))
        below = np.flatnonzero(y[start:] <= n_t)
        b = x_max if len(below) == 0 else float(grid[start + below[0]])
        return self.axis.to_si(max(b, x_now) if y[min(start, len(y) - 1)] > n_t else x_now)

    def predict_from(self, x_si: np.ndarray, n: np.ndarray) -> Prediction:
        x_now = float(np.max(x_si)) if len(x_si) else 0.0
        curve = self.fit_curve(x_si, n)
        if curve is None:
            return Prediction(False, math.nan, False, "no valid model: too few or degenerate samples", x_now)
        b = self.boundary_of(curve, self.n_t, x_now)
        return Prediction(True, b, b > x_now + self.step - 1e-12, "ok", x_now)
