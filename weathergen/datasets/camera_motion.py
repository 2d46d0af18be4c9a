"""Camera motion between two frames from frame-1 3D points and their frame-2 pixels (OpenCV).

Datasets without poses (KITTI) give, for many pixels, a 3D point in camera 1 (from the frame's
depth) and the pixel where that point appears in frame 2 (from ground-truth flow, or from feature
matching where no flow exists). The camera motion ``cam2_from_cam1`` is the rigid transform that
projects the points onto those pixels: a perspective-n-point problem, solved robustly by OpenCV's
``solvePnPRansac`` (minimal samples, consensus within ``threshold_px``) and then refined by
Levenberg-Marquardt on the inliers' reprojection error (``solvePnPRefineLM``). Moving objects
are outliers of the background's motion, so an object map is a help, not a requirement.

Several candidates are scored by the same rule, on every correspondence: the number of inliers
(reprojection error below ``threshold_px``), then their RMS error. The RANSAC hypothesis, its
refinement and refinements on re-selected inliers are all candidates, and the best one is kept
(never simply the last).

Errors are reprojection errors in frame-2 pixels, where the data was measured. Everything here is
float64 numpy; no file I/O.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from ..errors import ConfigError


@dataclass(frozen=True)
class FitSettings:
    """Thresholds of the camera-motion fit (library defaults; the CLI exposes each).

    ``threshold_px``: a correspondence agrees with a motion when its reprojection error is below
    this. ``min_points``: fewer usable correspondences refuse the pair. ``min_inlier_fraction``:
    a fit whose inliers are fewer than this fraction of the correspondences is refused.
    ``max_rms_px``: a fit whose inlier RMS error exceeds this is refused. ``iterations`` and
    ``confidence``: RANSAC's limits. ``max_points``: correspondences beyond this are thinned (a
    fixed, seeded subset) for RANSAC; scores always use all of them.
    """

    threshold_px: float = 2.0
    min_points: int = 200
    min_inlier_fraction: float = 0.5
    max_rms_px: float = 1.5
    iterations: int = 2000
    confidence: float = 0.9999
    max_points: int = 20000
    seed: int = 0

    def __post_init__(self):
        if not (np.isfinite(self.threshold_px) and self.threshold_px > 0):
            raise ConfigError(f"fit threshold must be a positive number of pixels, got {self.threshold_px}")
        if int(self.min_points) < 6:
            # a pose has 6 degrees of freedom; RANSAC's samples and the refinement need 6 points
            raise ConfigError(f"minimum fit points must be at least 6, got {self.min_points}")
        if not 0 < self.min_inlier_fraction <= 1:
            raise ConfigError(f"minimum inlier fraction must be in (0, 1], got {self.min_inlier_fraction}")
        if not (np.isfinite(self.max_rms_px) and self.max_rms_px > 0):
            raise ConfigError(f"maximum fit RMS must be a positive number of pixels, got {self.max_rms_px}")
        if int(self.iterations) < 1:
            raise ConfigError(f"fit iterations must be at least 1, got {self.iterations}")
        if not 0 < self.confidence < 1:
            raise ConfigError(f"fit confidence must be in (0, 1), got {self.confidence}")
        if int(self.max_points) < 6:
            raise ConfigError(f"max_points must be at least 6, got {self.max_points}")

    def describe(self) -> dict:
        return {"fit_threshold_px": self.threshold_px, "fit_min_points": int(self.min_points),
                "fit_min_inlier_fraction": self.min_inlier_fraction,
                "fit_max_rms_px": self.max_rms_px}


@dataclass(frozen=True)
class MotionFit:
    """Result of :func:`fit_motion_pnp`.

    Shape: ``cam2_from_cam1`` (4, 4) float64; ``inliers`` (N,) bool over the correspondences;
    ``errors_px`` (N,) reprojection error of each (inf behind the camera).
    """

    cam2_from_cam1: np.ndarray
    inliers: np.ndarray
    errors_px: np.ndarray
    threshold_px: float
    source: str = "flow"

    @property
    def n_points(self) -> int:
        return int(self.inliers.size)

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())

    @property
    def inlier_fraction(self) -> float:
        return self.n_inliers / max(self.n_points, 1)

    @property
    def rms_px(self) -> float:
        """Root-mean-square reprojection error of the inliers (inf without inliers)."""
        e = self.errors_px[self.inliers]
        return float(np.sqrt(np.mean(e ** 2))) if e.size else float("inf")

    @property
    def median_px(self) -> float:
        """Median reprojection error over every correspondence."""
        return float(np.median(self.errors_px)) if self.errors_px.size else float("inf")

    @property
    def translation(self) -> np.ndarray:
        """Translation of ``cam2_from_cam1`` (scene units). Shape: (3,)."""
        return self.cam2_from_cam1[:3, 3].copy()

    @property
    def rotation_deg(self) -> float:
        """Angle of the rotation of ``cam2_from_cam1`` in degrees."""
        cos = (np.trace(self.cam2_from_cam1[:3, :3]) - 1) / 2
        return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))

    def summary(self) -> dict:
        """Plain-data description for manifests and messages."""
        return {"method": "opencv-pnp-ransac+lm", "correspondences": self.source,
                "translation": [round(float(v), 5) for v in self.translation],
                "rotation_deg": round(self.rotation_deg, 4),
                "points": self.n_points, "inliers": self.n_inliers,
                "inlier_fraction": round(self.inlier_fraction, 4),
                "rms_px": round(self.rms_px, 4), "median_px": round(self.median_px, 4),
                "threshold_px": self.threshold_px}

    def motion_text(self) -> str:
        """The motion in words: translation (scene units) and rotation angle."""
        t = self.translation
        return f"t=({t[0]:+.3f}, {t[1]:+.3f}, {t[2]:+.3f}), rotation {self.rotation_deg:.2f}°"

    def describe(self) -> str:
        """One line for messages and tables: motion, inliers, error."""
        return (f"{self.motion_text()}, {100 * self.inlier_fraction:.0f}% of {self.n_points} "
                f"points within {self.threshold_px:g} px, inlier RMS {self.rms_px:.2f} px")


def reprojection_errors(cam2_from_cam1: np.ndarray, points1: np.ndarray, pixels2: np.ndarray,
                        intrinsics: np.ndarray) -> np.ndarray:
    """Pixel distance between observed frame-2 pixels and the moved, projected frame-1 points.

    Shape: cam2_from_cam1 (4, 4); points1 (N, 3); pixels2 (N, 2); intrinsics (3, 3) -> (N,)
    (inf where the moved point is not in front of camera 2).
    """
    moved = points1 @ cam2_from_cam1[:3, :3].T + cam2_from_cam1[:3, 3]
    z = moved[:, 2]
    k = intrinsics
    with np.errstate(divide="ignore", invalid="ignore"):
        x, y = moved[:, 0] / z, moved[:, 1] / z
        u = k[0, 0] * x + k[0, 1] * y + k[0, 2]
        v = k[1, 1] * y + k[1, 2]
        err = np.hypot(u - pixels2[:, 0], v - pixels2[:, 1])
    return np.where((z > 1e-9) & np.isfinite(err), err, np.inf)


def _pose(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3, 1))[0]
    out[:3, 3] = np.asarray(tvec, np.float64).ravel()
    return out


def fit_motion_pnp(points1: np.ndarray, pixels2: np.ndarray, intrinsics: np.ndarray,
                   settings: FitSettings = FitSettings(), *, source: str = "flow",
                   initial: Optional[np.ndarray] = None) -> MotionFit:
    """Robust ``cam2_from_cam1`` from frame-1 camera points and the frame-2 pixels they appear at.

    Shape: points1 (N, 3) camera-1 coordinates; pixels2 (N, 2); intrinsics (3, 3).
    ``initial`` (4, 4) is an extra candidate (for example a motion known roughly).
    Deterministic: RANSAC runs on a seeded subset and OpenCV's own generator is seeded too.
    Raises ValueError for fewer than 6 correspondences (callers check ``min_points`` first).
    """
    p1 = np.ascontiguousarray(points1, np.float64)
    q2 = np.ascontiguousarray(pixels2, np.float64)
    if p1.ndim != 2 or p1.shape[1] != 3 or q2.shape != (len(p1), 2):
        raise ValueError(f"expected (N, 3) points and (N, 2) pixels, got {p1.shape} and {q2.shape}")
    n = len(p1)
    if n < 6:
        raise ValueError(f"a camera-motion fit needs at least 6 correspondences, got {n}")
    k = np.asarray(intrinsics, np.float64)
    thr = float(settings.threshold_px)

    rng = np.random.default_rng(settings.seed)
    sub = np.sort(rng.choice(n, size=settings.max_points, replace=False)) if n > settings.max_points \
        else np.arange(n)
    candidates = [] if initial is None else [np.asarray(initial, np.float64)]
    cv2.setRNGSeed(int(settings.seed))
    ok, rvec, tvec, _ = cv2.solvePnPRansac(
        p1[sub], q2[sub], k, None, iterationsCount=int(settings.iterations),
        reprojectionError=thr, confidence=float(settings.confidence), flags=cv2.SOLVEPNP_EPNP)
    if ok:
        candidates.append(_pose(rvec, tvec))

    best = None

    def consider(pose):
        nonlocal best
        err = reprojection_errors(pose, p1, q2, k)
        inl = err < thr
        rms = float(np.sqrt(np.mean(err[inl] ** 2))) if inl.any() else np.inf
        key = (int(inl.sum()), -rms)
        if best is None or key > best[0]:
            best = (key, pose, err, inl)
        return inl

    for pose in candidates:
        _refine(pose, p1, q2, k, consider)
    if best is None:
        # RANSAC found no consensus at all: report the identity with its (large) errors
        pose = np.eye(4)
        err = reprojection_errors(pose, p1, q2, k)
        best = (None, pose, err, err < thr)
    _, pose, err, inl = best
    return MotionFit(cam2_from_cam1=pose, inliers=inl, errors_px=err, threshold_px=thr, source=source)


def _refine(pose: np.ndarray, p1: np.ndarray, q2: np.ndarray, k: np.ndarray, consider) -> None:
    """Levenberg-Marquardt on the inliers, re-selecting them until the set settles; every step
    is handed to ``consider`` (which keeps the best and returns its inliers)."""
    inl = consider(pose)
    for _ in range(5):
        if inl.sum() < 6:
            break
        r, _ = cv2.Rodrigues(pose[:3, :3])
        t = pose[:3, 3].reshape(3, 1).copy()
        r, t = cv2.solvePnPRefineLM(p1[inl], q2[inl], k, None, r, t)
        pose = _pose(r, t)
        new = consider(pose)
        if np.array_equal(new, inl):
            break
        inl = new


def check_fit(fit: MotionFit, settings: FitSettings) -> Optional[str]:
    """None when the fit meets the thresholds, else a description of what it misses (with figures)."""
    if fit.inlier_fraction < settings.min_inlier_fraction:
        return (f"only {100 * fit.inlier_fraction:.1f}% of {fit.n_points} correspondences agree with "
                f"one camera motion within {fit.threshold_px:g} px (at least "
                f"{100 * settings.min_inlier_fraction:g}% required); best motion {fit.motion_text()}, "
                f"inlier RMS {fit.rms_px:.2f} px, median error {fit.median_px:.2f} px")
    if fit.rms_px > settings.max_rms_px:
        return (f"the inliers' reprojection error is {fit.rms_px:.2f} px RMS, above the "
                f"{settings.max_rms_px:g} px allowed; motion {fit.motion_text()}, "
                f"{100 * fit.inlier_fraction:.1f}% of {fit.n_points} correspondences within "
                f"{fit.threshold_px:g} px")
    return None


def match_features(image1: np.ndarray, image2: np.ndarray, *, max_features: int = 8000,
                   ratio: float = 0.8) -> tuple[np.ndarray, np.ndarray]:
    """Pixel correspondences between two frames by SIFT features (OpenCV).

    The frames are contrast-equalised (CLAHE) first; matches pass Lowe's ratio test and must be
    mutual nearest neighbours.
    Shape: images (H, W, 3) float in [0, 1] -> ``(pixels1 (M, 2), pixels2 (M, 2))`` float64.
    """
    # Local contrast equalisation first: dark or hazy frames give SIFT few features otherwise.
    clahe = cv2.createCLAHE(clipLimit=2.0, tileGridSize=(8, 8))
    grey = [clahe.apply(cv2.cvtColor((np.clip(im, 0, 1) * 255 + 0.5).astype(np.uint8),
                                     cv2.COLOR_RGB2GRAY)) for im in (image1, image2)]
    sift = cv2.SIFT_create(nfeatures=max_features)
    (kp1, d1), (kp2, d2) = (sift.detectAndCompute(g, None) for g in grey)
    if d1 is None or d2 is None or len(kp1) < 2 or len(kp2) < 2:
        return np.zeros((0, 2)), np.zeros((0, 2))
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    forward = matcher.knnMatch(d1, d2, k=2)
    backward = {m.queryIdx: m.trainIdx for m in matcher.match(d2, d1)}
    keep = [m[0] for m in forward
            if len(m) == 2 and m[0].distance < ratio * m[1].distance
            and backward.get(m[0].trainIdx) == m[0].queryIdx]
    pix1 = np.array([kp1[m.queryIdx].pt for m in keep], np.float64).reshape(-1, 2)
    pix2 = np.array([kp2[m.trainIdx].pt for m in keep], np.float64).reshape(-1, 2)
    return pix1, pix2


def backproject_pixels(pixels: np.ndarray, z: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
    """Camera points of pixels at camera-z depths. Shape: (N, 2), (N,), (3, 3) -> (N, 3)."""
    k = intrinsics
    y = (pixels[:, 1] - k[1, 2]) / k[1, 1]
    x = (pixels[:, 0] - k[0, 2] - k[0, 1] * y) / k[0, 0]
    return np.stack([x * z, y * z, z], 1)
