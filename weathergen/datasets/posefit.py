"""Camera motion between two stereo frames, from 3D point correspondences on the static scene.

The motion is the rigid transform ``cam2_from_cam1`` that best maps the frame-1 points onto the
frame-2 points, found by least squares (Arun, Huang & Blostein 1987; the Kabsch solution via an
SVD of the weighted cross-covariance) inside a RANSAC loop, then refined on the inliers.

Errors are measured where the data was measured: a stereo point is a pixel ``(u, v)`` and a
disparity ``d = fx B / z``, so the residual of a correspondence is the distance, in pixels, between
the observed ``(u, v, d)`` in frame 2 and the one predicted by moving the frame-1 point. A 3D
distance would let far points (whose depth is uncertain to metres) dominate the fit.

Everything here is plain numpy in float64; no file I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ShapeError


@dataclass(frozen=True)
class RigidFit:
    """Result of :func:`fit_camera_motion`.

    Shape: ``cam2_from_cam1`` (4, 4) float64; ``inliers`` (N,) bool over the input points.
    ``rms_px`` is the root-mean-square stereo residual over the inliers and ``median_px`` the
    median over all points, both in pixels.
    """

    cam2_from_cam1: np.ndarray
    inliers: np.ndarray
    rms_px: float
    median_px: float
    threshold_px: float

    @property
    def n_points(self) -> int:
        return int(self.inliers.size)

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())

    @property
    def inlier_fraction(self) -> float:
        return self.n_inliers / max(self.n_points, 1)

    def summary(self) -> dict:
        """Plain-data description, for manifests and messages."""
        return {"method": "rigid-fit", "points": self.n_points, "inliers": self.n_inliers,
                "inlier_fraction": round(self.inlier_fraction, 4), "rms_px": round(self.rms_px, 4),
                "median_px": round(self.median_px, 4), "threshold_px": self.threshold_px}


def kabsch(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Weighted least-squares rigid transform with ``dst ≈ R src + t``.

    Shape: src, dst (N, 3), N >= 3; weights (N,) non-negative or None -> (4, 4) float64.
    A reflection is never returned (the sign of the last singular vector is corrected).
    """
    src = np.asarray(src, np.float64)
    dst = np.asarray(dst, np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ShapeError(f"kabsch needs two (N, 3) arrays with N >= 3, got {src.shape} and {dst.shape}")
    w = np.ones(len(src)) if weights is None else np.asarray(weights, np.float64)
    w = w / w.sum()
    c_src, c_dst = w @ src, w @ dst
    cov = (src - c_src).T @ ((dst - c_dst) * w[:, None])       # (3, 3) cross-covariance
    u, _, vt = np.linalg.svd(cov)
    flip = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    rot = vt.T @ np.diag([1.0, 1.0, flip]) @ u.T
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = c_dst - rot @ c_src
    return out


def _kabsch_minimal(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unweighted Kabsch for a batch of small samples. Shape: (B, M, 3) each -> R (B, 3, 3), t (B, 3)."""
    c_src, c_dst = src.mean(1, keepdims=True), dst.mean(1, keepdims=True)
    cov = (src - c_src).transpose(0, 2, 1) @ (dst - c_dst)
    u, _, vt = np.linalg.svd(cov)
    flip = np.sign(np.linalg.det(vt.transpose(0, 2, 1) @ u.transpose(0, 2, 1)))
    flip[flip == 0] = 1.0
    d = np.ones((len(src), 3))
    d[:, 2] = flip
    rot = vt.transpose(0, 2, 1) @ (d[:, :, None] * u.transpose(0, 2, 1))
    t = c_dst[:, 0] - np.einsum("bij,bj->bi", rot, c_src[:, 0])
    return rot, t


def _stereo_obs(points: np.ndarray, k: np.ndarray, baseline: float) -> np.ndarray:
    """``(u, v, disparity)`` of camera points. Shape: (..., N, 3) -> (..., N, 3); z <= 0 gives inf."""
    z = points[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = k[0, 0] * points[..., 0] / z + k[0, 1] * points[..., 1] / z + k[0, 2]
        v = k[1, 1] * points[..., 1] / z + k[1, 2]
        d = k[0, 0] * baseline / z
    out = np.stack((u, v, d), axis=-1)
    out[z <= 0] = np.inf
    return out


def stereo_residuals(cam2_from_cam1: np.ndarray, points1: np.ndarray, points2: np.ndarray,
                     intrinsics: np.ndarray, baseline: float) -> np.ndarray:
    """Pixel distance between observed and predicted ``(u, v, disparity)`` in frame 2.

    Shape: cam2_from_cam1 (4, 4); points1, points2 (N, 3) camera coordinates; intrinsics (3, 3)
    -> (N,) pixels (inf where the moved point falls behind the camera).
    """
    moved = points1 @ cam2_from_cam1[:3, :3].T + cam2_from_cam1[:3, 3]
    k = np.asarray(intrinsics, np.float64)
    diff = _stereo_obs(moved, k, baseline) - _stereo_obs(points2, k, baseline)
    with np.errstate(invalid="ignore"):
        res = np.linalg.norm(diff, axis=-1)
    return np.where(np.isfinite(res), res, np.inf)


def fit_camera_motion(points1: np.ndarray, points2: np.ndarray, intrinsics: np.ndarray,
                      baseline: float, *, threshold_px: float = 2.0, max_hypotheses: int = 2048,
                      confidence: float = 0.999, scoring_points: int = 3000,
                      seed: int = 0) -> RigidFit:
    """Robust camera motion ``cam2_from_cam1`` from static 3D correspondences.

    Shape: points1, points2 (N, 3) camera-1 and camera-2 coordinates of the same scene points
    (N >= 3); intrinsics (3, 3); baseline in the units of the points.

    RANSAC on minimal 3-point samples (scored on at most ``scoring_points`` points with a truncated
    quadratic cost, stopping once ``confidence`` is reached), then iterative re-fitting on all points
    within ``threshold_px``, each point weighted by ``1/z²`` so that the 3D least squares
    approximates a least squares in pixels. Deterministic for a given ``seed``.
    """
    p1 = np.asarray(points1, np.float64)
    p2 = np.asarray(points2, np.float64)
    if p1.shape != p2.shape or p1.ndim != 2 or p1.shape[1] != 3:
        raise ShapeError(f"expected two (N, 3) point arrays, got {p1.shape} and {p2.shape}")
    n = len(p1)
    if n < 3:
        raise ValueError(f"a rigid fit needs at least 3 correspondences, got {n}")
    k = np.asarray(intrinsics, np.float64)
    rng = np.random.default_rng(seed)

    score_idx = rng.choice(n, size=min(n, scoring_points), replace=False)
    s1, s2 = p1[score_idx], p2[score_idx]
    obs2 = _stereo_obs(s2, k, baseline)
    best_cost, best, done, needed, batch = np.inf, np.eye(4), 0, max_hypotheses, 128
    while done < min(needed, max_hypotheses):
        # three distinct points per hypothesis
        picks = np.stack([rng.choice(n, size=3, replace=False) for _ in range(batch)])
        rot, t = _kabsch_minimal(p1[picks], p2[picks])
        moved = np.einsum("bij,nj->bni", rot, s1) + t[:, None, :]          # (B, M, 3)
        diff = _stereo_obs(moved, k, baseline) - obs2[None]
        with np.errstate(invalid="ignore"):
            r2 = np.nan_to_num((diff ** 2).sum(-1), nan=np.inf, posinf=np.inf)
        cost = np.minimum(r2, threshold_px ** 2).sum(1)
        i = int(np.argmin(cost))
        if cost[i] < best_cost:
            best_cost = cost[i]
            best = np.eye(4)
            best[:3, :3], best[:3, 3] = rot[i], t[i]
            ratio = float((r2[i] < threshold_px ** 2).mean())
            if ratio >= 1.0:
                needed = 0
            elif ratio > 0:
                needed = int(np.ceil(np.log(1 - confidence) / np.log(1 - ratio ** 3)))
        done += batch

    # Refine on every point: re-select inliers and re-fit until the inlier set settles.
    weights = 1.0 / np.maximum(0.5 * (p1[:, 2] + p2[:, 2]), 1e-9) ** 2
    fit = best
    inliers = stereo_residuals(fit, p1, p2, k, baseline) < threshold_px
    for _ in range(20):
        if inliers.sum() < 3:
            break
        fit = kabsch(p1[inliers], p2[inliers], weights[inliers])
        new = stereo_residuals(fit, p1, p2, k, baseline) < threshold_px
        if np.array_equal(new, inliers):
            break
        inliers = new
    res = stereo_residuals(fit, p1, p2, k, baseline)
    inliers = res < threshold_px
    rms = float(np.sqrt(np.mean(res[inliers] ** 2))) if inliers.any() else float("inf")
    return RigidFit(cam2_from_cam1=fit, inliers=inliers, rms_px=rms,
                    median_px=float(np.median(res)), threshold_px=float(threshold_px))
