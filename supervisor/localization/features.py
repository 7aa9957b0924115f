"""Feature extraction (CLAHE -> SIFT) and descriptor matching (k-NN + Lowe ratio, one-to-one).

Both objects are built once and reused for every frame: the CLAHE and SIFT
instances, and for matching against a fixed model the FLANN KD-tree index over
the model descriptors.
"""

from __future__ import annotations

import time

import cv2
import numpy as np

from supervisor.localization.settings import LocalizerSettings

Roi = tuple[int, int, int, int]  # (x, y, w, h) in full-image pixels

_FLANN_INDEX_KDTREE = 1


class FeatureExtractor:
    """CLAHE-equalised SIFT keypoints and descriptors of a mono8 image."""

    def __init__(self, settings: LocalizerSettings) -> None:
        self.settings = settings
        self._clahe = cv2.createCLAHE(clipLimit=settings.clahe_clip,
                                      tileGridSize=(settings.clahe_tile, settings.clahe_tile))
        self._sift = cv2.SIFT_create(nfeatures=settings.sift_nfeatures, nOctaveLayers=settings.sift_octave_layers,
                                     contrastThreshold=settings.sift_contrast_threshold,
                                     edgeThreshold=settings.sift_edge_threshold, sigma=settings.sift_sigma)
        self._eq: np.ndarray | None = None  # reused CLAHE output buffer
        self.last_timings: dict[str, float] = {}

    def equalize(self, gray: np.ndarray) -> np.ndarray:
        """CLAHE over the whole image (tiles are a fixed fraction of the full frame, so an ROI
        crop taken afterwards sees exactly the pixels a full-frame run would)."""
        if self._eq is None or self._eq.shape != gray.shape:
            self._eq = np.empty_like(gray)
        self._clahe.apply(gray, self._eq)
        return self._eq

    def detect(self, equalized: np.ndarray, roi: Roi | None = None) -> tuple[np.ndarray, np.ndarray]:
        """SIFT on an already equalised image, optionally inside `roi` (keypoints in full-image pixels)."""
        x0 = y0 = 0
        img = equalized
        if roi is not None:
            x0, y0, w, h = roi
            img = equalized[y0:y0 + h, x0:x0 + w]
        kps, desc = self._sift.detectAndCompute(img, None)
        if desc is None or len(kps) == 0:
            return np.empty((0, 2), np.float32), np.empty((0, 128), np.float32)
        pts = cv2.KeyPoint_convert(kps)
        if x0 or y0:
            pts += np.array([x0, y0], np.float32)
        return pts.astype(np.float32, copy=False), np.ascontiguousarray(desc, dtype=np.float32)

    def extract(self, gray: np.ndarray, roi: Roi | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(keypoints Nx2 float32 in full-image pixels, descriptors Nx128 float32); timings in `last_timings`."""
        t0 = time.perf_counter()
        eq = self.equalize(gray)
        t1 = time.perf_counter()
        out = self.detect(eq, roi)
        t2 = time.perf_counter()
        self.last_timings = {"clahe": t1 - t0, "sift": t2 - t1}
        return out


class DescriptorMatcher:
    """Matches query descriptors against a fixed train set (the model): 2-NN, Lowe ratio
    test, then one-to-one (each train feature keeps only its closest query).

    With `kind="flann"` the KD-tree index over the train descriptors is built once here;
    `kind="bf"` is exact brute force (slower, the reference).
    """

    def __init__(self, train: np.ndarray, ratio: float, kind: str = "flann", trees: int = 4,
                 checks: int = 64) -> None:
        if kind not in ("flann", "bf"):
            raise ValueError(f"unknown matcher {kind!r}")
        self.ratio = ratio
        self.kind = kind
        self._train = np.ascontiguousarray(train, dtype=np.float32)  # the index refers to this memory
        self.n_train = int(len(self._train))
        self._checks = {"checks": int(checks)}
        self._index = None
        self._bf = None
        if self.n_train >= 2:
            if kind == "flann":
                # The randomised KD-trees draw from OpenCV's global RNG: seed it so the same model gives
                # the same index (and the same n_i) whatever ran before in this process.
                cv2.setRNGSeed(0x5EED)
                self._index = cv2.flann_Index(self._train, {"algorithm": _FLANN_INDEX_KDTREE, "trees": int(trees)})
            else:
                self._bf = cv2.BFMatcher(cv2.NORM_L2, crossCheck=False)

    def knn2(self, query: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(indices Nx2, squared L2 distances Nx2) of the two nearest train descriptors."""
        query = np.ascontiguousarray(query, dtype=np.float32)
        if self._index is not None:
            idx, dist = self._index.knnSearch(query, 2, params=self._checks)
            return idx.astype(np.intp, copy=False), dist
        knn = self._bf.knnMatch(query, self._train, k=2)
        idx = np.array([[m.trainIdx for m in pair] for pair in knn], np.intp).reshape(-1, 2)
        dist = np.array([[m.distance for m in pair] for pair in knn], np.float32).reshape(-1, 2) ** 2
        return idx, dist

    def match(self, query: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(query indices, train indices) of the accepted matches, as int arrays of equal length."""
        qi, ti, _ = self.match_knn(query)
        return qi, ti

    def match_knn(self, query: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray] | None]:
        """`match`, plus the 2-NN results it was drawn from (None when there was nothing to search)."""
        if self.n_train < 2 or len(query) == 0:
            return np.empty(0, np.intp), np.empty(0, np.intp), None
        knn = self.knn2(query)
        return (*ratio_one_to_one(*knn, self.ratio), knn)


def ratio_one_to_one(idx: np.ndarray, dist_sq: np.ndarray, ratio: float, also: np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Lowe ratio test on 2-NN results (squared distances), and `also` (a boolean per query) when given,
    then keep the closest query per train index."""
    ok = dist_sq[:, 0] < (ratio * ratio) * dist_sq[:, 1]
    if also is not None:
        ok &= also
    q = np.flatnonzero(ok)
    if len(q) == 0:
        return np.empty(0, np.intp), np.empty(0, np.intp)
    t = idx[q, 0]
    d = dist_sq[q, 0]
    order = np.lexsort((d, t))  # by train index, then distance
    t_sorted = t[order]
    first = np.ones(len(order), bool)
    first[1:] = t_sorted[1:] != t_sorted[:-1]
    keep = np.sort(order[first])
    return q[keep].astype(np.intp), t[keep].astype(np.intp)


def guided_matches(points_px: np.ndarray, knn_idx: np.ndarray, knn_dist_sq: np.ndarray, projected_px: np.ndarray,
                   radius_px: float, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """Nearest-neighbour matches verified by projection: (keypoint indices, model indices), one-to-one.

    A keypoint is paired with its nearest model descriptor (`knn_idx[:, 0]`, from `knn2`) when it
    passes a ratio test at `ratio` (looser than the global one) and lies within `radius_px` of that
    model point's projection (`projected_px`, rows of NaN never match). The window is the filter: an
    unrelated nearest neighbour lands inside a few pixels of its own model point only by chance
    (about radius^2 / area of the view), so even ambiguous descriptors are safe to use, whereas pairing
    a model point with whichever keypoint is near its projection would follow any pose it is given.
    A model point claimed by several keypoints keeps the nearest descriptor.
    """
    if len(points_px) == 0:
        return np.empty(0, np.intp), np.empty(0, np.intp)
    with np.errstate(invalid="ignore"):  # NaN projections compare False
        near = np.sum((projected_px[knn_idx[:, 0]] - points_px) ** 2, axis=1) <= radius_px * radius_px
    return ratio_one_to_one(knn_idx, knn_dist_sq, ratio, near)


def mutual_matches(desc_a: np.ndarray, desc_b: np.ndarray, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact ratio-test matches a -> b that are also mutual nearest neighbours (b -> a).

    Used for model building, where accuracy matters more than time.
    """
    if len(desc_a) < 2 or len(desc_b) < 2:
        return np.empty(0, np.intp), np.empty(0, np.intp)
    ia, ib = DescriptorMatcher(desc_b, ratio, kind="bf").match(desc_a)
    back_idx, _ = DescriptorMatcher(desc_a, 1.0, kind="bf").knn2(desc_b)
    keep = back_idx[ib, 0] == ia
    return ia[keep], ib[keep]
