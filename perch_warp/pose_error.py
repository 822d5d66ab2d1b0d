"""Pose errors and their summaries, in the style of bop_toolkit_lib's `pose_error`.

Everything here is in **metres** and radians: poses are model -> camera
(`R` 3x3, `t` (3,) metres), model points are (N, 3) metres in the model frame.
(BOP files carry millimetres; `perch_warp.bop` converts at the boundary.)

ADD   mean over model points of |(R_est p + t_est) - (R_gt p + t_gt)|.
ADD-S mean over model points p of the distance from R_gt p + t_gt to the
      *closest* point of the model under the estimated pose (BOP's `adi`,
      PoseCNN's ADD-S): indifferent to symmetries that map the model onto itself.
AUC   area under the accuracy-vs-threshold curve for thresholds 0..0.1 m, in %,
      see `auc` for the exact discretisation.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

#: Models are subsampled to at most this many points for ADD/ADD-S (see `subsample_points`).
DEFAULT_MAX_POINTS = 5000


def transform_points(pts_m: np.ndarray, R: np.ndarray, t_m: np.ndarray) -> np.ndarray:
    """Model points (N, 3, metres) under the pose (R, t_m) -> camera frame (N, 3, metres)."""
    R = np.asarray(R, dtype=np.float64).reshape(3, 3)
    t_m = np.asarray(t_m, dtype=np.float64).reshape(3)
    return np.asarray(pts_m, dtype=np.float64) @ R.T + t_m


def subsample_points(pts_m: np.ndarray, max_points: int = DEFAULT_MAX_POINTS, seed: int = 0) -> np.ndarray:
    """At most `max_points` of the (N, 3) points, chosen deterministically.

    A fixed-seed random subset without replacement, kept in the input order, so the
    same model always gives the same subset. Mesh vertices are the BOP convention for
    ADD/ADD-S; a few thousand of them keep the nearest-neighbour search to
    milliseconds while changing ADD-S by far less than a millimetre on YCB-size
    objects (the subset is dense compared with a 2 cm threshold).
    """
    pts_m = np.asarray(pts_m, dtype=np.float64).reshape(-1, 3)
    if len(pts_m) <= max_points:
        return pts_m
    idx = np.sort(np.random.default_rng(seed).choice(len(pts_m), size=max_points, replace=False))
    return pts_m[idx]


def add(R_est: np.ndarray, t_est_m: np.ndarray, R_gt: np.ndarray, t_gt_m: np.ndarray, pts_m: np.ndarray) -> float:
    """ADD (metres): mean distance between corresponding model points under the two poses."""
    e = transform_points(pts_m, R_est, t_est_m) - transform_points(pts_m, R_gt, t_gt_m)
    return float(np.linalg.norm(e, axis=1).mean())


def adi(R_est: np.ndarray, t_est_m: np.ndarray, R_gt: np.ndarray, t_gt_m: np.ndarray, pts_m: np.ndarray) -> float:
    """ADD-S (metres): for each model point under the ground-truth pose, the distance to the
    closest model point under the estimated pose, averaged (KD-tree nearest neighbours).

    Like BOP's `adi`, the points are used as given; pass `subsample_points(...)` for speed.
    """
    pts_est = transform_points(pts_m, R_est, t_est_m)
    pts_gt = transform_points(pts_m, R_gt, t_gt_m)
    dist, _ = cKDTree(pts_est).query(pts_gt, k=1)
    return float(np.mean(dist))


#: The name used in the YCB-Video / PoseCNN papers.
add_s = adi


def translation_error(t_est_m: np.ndarray, t_gt_m: np.ndarray) -> float:
    """Euclidean distance (metres) between the two translations (model origins)."""
    return float(np.linalg.norm(np.asarray(t_est_m, dtype=np.float64) - np.asarray(t_gt_m, dtype=np.float64)))


def yaw_error(yaw_est_rad: float, yaw_gt_rad: float) -> float:
    """Absolute yaw difference (radians) wrapped to [0, pi]. Symmetries are not taken into account."""
    d = (float(yaw_est_rad) - float(yaw_gt_rad)) % (2 * np.pi)
    return float(min(d, 2 * np.pi - d))


def _clean_errors(errors_m) -> np.ndarray:
    # A failed estimate (NaN / None) counts as wrong at every threshold.
    e = np.asarray([np.inf if v is None else v for v in np.ravel(errors_m)], dtype=np.float64)
    e[~np.isfinite(e)] = np.inf
    return e


def accuracy_curve(errors_m, thresholds_m) -> np.ndarray:
    """Fraction (0..1) of errors strictly below each threshold (metres); NaN/inf errors never count."""
    e = _clean_errors(errors_m)
    thr = np.asarray(thresholds_m, dtype=np.float64)
    if e.size == 0:
        return np.full(thr.shape, np.nan)
    return (e[None, :] < thr.reshape(-1, 1)).mean(axis=1).reshape(thr.shape)


def accuracy_below(errors_m, threshold_m: float = 0.02) -> float:
    """Percentage of errors strictly below `threshold_m` (the thesis's "ADD-S < 2 cm")."""
    return float(100.0 * accuracy_curve(errors_m, [threshold_m])[0])


def auc(errors_m, max_threshold_m: float = 0.1) -> float:
    """Area under the accuracy-vs-threshold curve for thresholds in [0, max_threshold_m], in %.

    Discretisation: none -- the exact integral of the empirical step curve.
    With acc(tau) = fraction of errors e_i < tau,

        AUC = 100 / T * integral_0^T acc(tau) dtau = 100 * mean_i max(0, 1 - e_i / T),

    because each error contributes (T - e_i) to the integral when e_i < T. NaN/inf
    errors contribute 0. This is what PoseCNN's curve means; its toolbox
    (`VOCap`, see `auc_posecnn`) evaluates the same curve with a right-end rule that
    reads slightly higher (by up to 100/n points for n errors).
    """
    e = _clean_errors(errors_m)
    if e.size == 0:
        return float("nan")
    return float(100.0 * np.mean(np.clip(1.0 - e / max_threshold_m, 0.0, 1.0)))


def auc_shares(errors_m, max_threshold_m: float = 0.1) -> np.ndarray:
    """Each error's share (%) of `auc`, whose mean it is: 100 max(0, 1 - e / T); 0 for NaN/inf/None.
    For intervals and paired differences over targets (perch_warp.eval.metrics)."""
    return 100.0 * np.clip(1.0 - _clean_errors(errors_m) / max_threshold_m, 0.0, None)


def below_shares(errors_m, threshold_m: float = 0.02) -> np.ndarray:
    """Each error's share (%) of `accuracy_below`, whose mean it is: 100 where e < threshold_m, else 0."""
    return 100.0 * (_clean_errors(errors_m) < threshold_m)


def auc_posecnn(errors_m, max_threshold_m: float = 0.1) -> float:
    """AUC in % exactly as the YCB-Video toolbox computes it (PoseCNN's `VOCap`).

    Errors above the threshold are dropped, the rest sorted (d_1 <= ... <= d_k) with
    accuracy j/n at d_j, and the area is summed as sum_j (d_j - d_{j-1}) * j/n
    + (T - d_k) * k/n, normalised by T. On (d_{j-1}, d_j] the true accuracy is (j-1)/n,
    so this reads higher than `auc` by d_k / (T n); e.g. one error of 0.05 m gives
    100 here and 50 in `auc`. Given for comparison with published numbers.
    """
    e = _clean_errors(errors_m)
    n = e.size
    if n == 0:
        return float("nan")
    d = np.sort(e[e <= max_threshold_m])
    if d.size == 0:
        return 0.0
    acc = np.arange(1, d.size + 1) / n
    mrec = np.concatenate([[0.0], d, [max_threshold_m]])
    mpre = np.concatenate([[0.0], acc, [acc[-1]]])
    mpre = np.maximum.accumulate(mpre)
    i = np.nonzero(mrec[1:] != mrec[:-1])[0] + 1
    return float(100.0 * np.sum((mrec[i] - mrec[i - 1]) * mpre[i]) / max_threshold_m)
