"""The bundled demo scene: two small ray-cast scenes of our own, stored in Sintel layout.

Each scene is built from textured planes and boxes, seen by a moving camera (rotation and
translation; the courtyard camera is also rolled and tilted). Everything is computed from the
geometry, so depth, cameras and ground-truth flow are exact:

- the image is the average of 2x2 shaded rays per pixel (anti-aliased);
- depth is the camera-z distance of the surface hit by the ray through the pixel centre;
- flow projects that 3D hit point into the next camera (the scene is static);
- ``occlusions/`` marks pixels whose surface point is hidden or outside the image in the next frame.

The world is z-up (like the Blender scenes behind Sintel). Textures are solid (a function of the 3D
point), so a surface looks the same from every camera. Generation is deterministic and takes about
a second; :func:`demo_root` generates the scene on first use into the user cache.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..io.images import write_png
from ..io.sintel_formats import write_cam, write_dpt, write_flo

#: Bump when the generator's output changes; part of the cache folder name.
DEMO_VERSION = 1
WIDTH, HEIGHT = 384, 176
FOCAL = 300.0
FRAMES = 4
SCENES = ("courtyard", "street")
#: World up axis of the demo scene.
WORLD_UP = np.array([0.0, 0.0, 1.0])


# -- geometry ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Material:
    color: tuple[float, float, float]
    pattern: str      # "noise", "bricks", "tiles" or "stripes"
    scale: float      # size of the pattern in scene units
    seed: int


@dataclass(frozen=True)
class Plane:
    """The plane ``x[axis] == offset``."""

    axis: int
    offset: float
    material: Material


@dataclass(frozen=True)
class Box:
    """An axis-aligned box from ``lo`` to ``hi``."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    material: Material


def intrinsics() -> np.ndarray:
    """The demo camera's ``(3, 3)`` intrinsics (square pixels, centred principal point)."""
    return np.array([[FOCAL, 0.0, (WIDTH - 1) / 2], [0.0, FOCAL, (HEIGHT - 1) / 2], [0.0, 0.0, 1.0]])


def look(position, yaw_deg: float, pitch_deg: float, roll_deg: float = 0.0) -> np.ndarray:
    """World-to-camera ``(4, 4)`` extrinsic of a z-up world camera.

    ``yaw`` turns left from +y about +z, ``pitch`` looks up, ``roll`` turns the image clockwise.
    """
    yaw, pitch, roll = np.deg2rad([yaw_deg, pitch_deg, roll_deg])
    forward = np.array([-np.sin(yaw) * np.cos(pitch), np.cos(yaw) * np.cos(pitch), np.sin(pitch)])
    right = np.cross(forward, WORLD_UP)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c, s = np.cos(roll), np.sin(roll)
    right, down = c * right + s * down, -s * right + c * down
    rot = np.stack([right, down, forward])          # rows: camera axes in world coordinates
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = -rot @ np.asarray(position, float)
    return out


def _scene(name: str):
    """Primitives and per-frame cameras of one demo scene."""
    mat = Material
    if name == "street":
        prims = [
            Plane(2, 0.0, mat((0.42, 0.40, 0.38), "tiles", 0.8, 1)),
            Plane(2, 7.0, mat((0.55, 0.68, 0.85), "noise", 3.0, 2)),
            Plane(0, -3.5, mat((0.70, 0.45, 0.35), "bricks", 0.5, 3)),
            Plane(0, 3.5, mat((0.80, 0.75, 0.60), "stripes", 1.3, 4)),
            Plane(1, 25.0, mat((0.50, 0.55, 0.60), "bricks", 0.9, 5)),
            Box((-3.0, 4.0, 0.0), (-1.8, 5.2, 1.1), mat((0.62, 0.48, 0.28), "stripes", 0.25, 6)),
            Box((1.2, 7.0, 0.0), (3.0, 9.5, 2.2), mat((0.30, 0.50, 0.35), "noise", 0.6, 7)),
            Box((-2.6, 11.0, 0.0), (-0.6, 12.0, 3.0), mat((0.75, 0.30, 0.25), "tiles", 0.5, 8)),
            Box((0.4, 15.0, 0.0), (2.4, 16.5, 1.5), mat((0.35, 0.40, 0.70), "noise", 0.4, 9)),
            Box((-0.5, 2.6, 0.0), (0.2, 3.2, 0.8), mat((0.85, 0.80, 0.30), "stripes", 0.15, 10)),
        ]
        cams = [look((0.3, 0.35 * i, 1.6), yaw_deg=-1.5 * i, pitch_deg=-4.0) for i in range(FRAMES)]
    elif name == "courtyard":
        prims = [
            Plane(2, 0.0, mat((0.50, 0.47, 0.40), "tiles", 1.1, 11)),
            Plane(2, 5.0, mat((0.75, 0.75, 0.72), "noise", 2.0, 12)),
            Plane(0, -5.0, mat((0.60, 0.62, 0.45), "stripes", 0.7, 13)),
            Plane(0, 5.0, mat((0.72, 0.52, 0.40), "bricks", 0.45, 14)),
            Plane(1, 14.0, mat((0.45, 0.50, 0.58), "bricks", 0.6, 15)),
            Box((-2.2, 5.0, 0.0), (-1.6, 5.6, 5.0), mat((0.82, 0.78, 0.70), "stripes", 0.2, 16)),
            Box((1.6, 7.5, 0.0), (2.2, 8.1, 5.0), mat((0.82, 0.78, 0.70), "stripes", 0.2, 17)),
            Box((-1.0, 9.0, 0.0), (1.5, 10.5, 1.2), mat((0.30, 0.55, 0.60), "noise", 0.5, 18)),
            Box((2.5, 3.0, 0.0), (3.6, 4.1, 0.9), mat((0.65, 0.35, 0.50), "tiles", 0.3, 19)),
            Box((-4.2, 10.0, 0.0), (-3.0, 12.5, 2.0), mat((0.40, 0.35, 0.30), "bricks", 0.35, 20)),
        ]
        cams = [look((-0.6 + 0.25 * i, 0.2 * i, 1.3), yaw_deg=2.0 * i - 3.0, pitch_deg=-8.0,
                     roll_deg=12.0 - 1.0 * i) for i in range(FRAMES)]
    else:
        raise ValueError(f"unknown demo scene {name!r}")
    return prims, cams


# -- ray casting ---------------------------------------------------------------------------------
def _cast(prims, origin: np.ndarray, dirs: np.ndarray):
    """Nearest hit of each ray. dirs (N, 3) world directions; returns t (N,), primitive (N,), normal (N, 3)."""
    n = dirs.shape[0]
    best_t = np.full(n, np.inf)
    best_i = np.full(n, -1)
    best_axis = np.zeros(n, dtype=np.int64)
    with np.errstate(divide="ignore", invalid="ignore"):
        for idx, p in enumerate(prims):
            if isinstance(p, Plane):
                t = (p.offset - origin[p.axis]) / dirs[:, p.axis]
                axis = np.full(n, p.axis)
            else:
                lo = (np.asarray(p.lo) - origin) / dirs
                hi = (np.asarray(p.hi) - origin) / dirs
                near, far = np.minimum(lo, hi), np.maximum(lo, hi)
                t = near.max(axis=1)
                axis = near.argmax(axis=1)
                t = np.where((t <= far.min(axis=1)) & (t > 0), t, np.inf)
            t = np.where(np.isfinite(t) & (t > 1e-6), t, np.inf)
            closer = t < best_t
            best_t = np.where(closer, t, best_t)
            best_i = np.where(closer, idx, best_i)
            best_axis = np.where(closer, axis, best_axis)
    if not np.isfinite(best_t).all():
        raise RuntimeError("demo scene has rays that hit nothing")
    normal = np.zeros((n, 3))
    normal[np.arange(n), best_axis] = 1.0
    normal *= -np.sign(np.einsum("ij,ij->i", normal, dirs))[:, None]   # face the camera
    return best_t, best_i, normal


def _value_noise(points: np.ndarray, seed: int, freq: float) -> np.ndarray:
    """Smooth 3D value noise in [0, 1] at ``points`` (N, 3)."""
    perm = np.random.default_rng(seed).permutation(256)
    values = np.random.default_rng(seed + 1000).random(256)
    q = points * freq
    base = np.floor(q).astype(np.int64)
    f = q - base
    s = f * f * (3 - 2 * f)
    out = np.zeros(len(points))
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                ix, iy, iz = base[:, 0] + dx, base[:, 1] + dy, base[:, 2] + dz
                h = perm[(perm[(perm[ix & 255] + iy) & 255] + iz) & 255]
                w = ((s[:, 0] if dx else 1 - s[:, 0]) * (s[:, 1] if dy else 1 - s[:, 1])
                     * (s[:, 2] if dz else 1 - s[:, 2]))
                out += w * values[h]
    return out


def _shade(prims, points: np.ndarray, prim_idx: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Colour of each hit point (N, 3) in [0, 1]."""
    light = np.array([0.35, -0.45, 0.82])
    light /= np.linalg.norm(light)
    lambert = 0.5 + 0.5 * np.clip(normals @ light, 0, 1)
    rgb = np.zeros((len(points), 3))
    for idx, p in enumerate(prims):
        sel = prim_idx == idx
        if not sel.any():
            continue
        m = p.material
        x = points[sel]
        fbm = (0.5 * _value_noise(x, m.seed, 1.0 / m.scale) + 0.3 * _value_noise(x, m.seed + 7, 3.0 / m.scale)
               + 0.2 * _value_noise(x, m.seed + 13, 9.0 / m.scale))
        # the two in-surface axes, ignoring the axis of the surface normal
        ax = np.argmax(np.abs(normals[sel]), axis=1)
        uv = np.stack([np.where(ax == 0, x[:, 1], x[:, 0]), np.where(ax == 2, x[:, 1], x[:, 2])], axis=1)
        uv = uv / m.scale
        if m.pattern == "bricks":
            row = np.floor(uv[:, 1] * 2)
            u = uv[:, 0] + 0.5 * (row % 2)
            mortar = (np.abs(uv[:, 1] * 2 - np.round(uv[:, 1] * 2)) < 0.06) | (np.abs(u - np.round(u)) < 0.03)
            pattern = np.where(mortar, 0.55, 1.0)
        elif m.pattern == "tiles":
            pattern = np.where((np.floor(uv[:, 0]) + np.floor(uv[:, 1])) % 2 == 0, 1.0, 0.72)
        elif m.pattern == "stripes":
            pattern = 0.8 + 0.2 * np.sin(2 * np.pi * uv[:, 0])
        else:
            pattern = np.ones(len(x))
        tone = pattern * (0.55 + 0.9 * (fbm - 0.5)) * lambert[sel]
        hue = 0.85 + 0.3 * _value_noise(x, m.seed + 29, 0.5 / m.scale)
        rgb[sel] = np.clip(np.asarray(m.color)[None] * tone[:, None] * np.stack([hue, np.ones_like(hue), 2 - hue], 1),
                           0, 1)
    return rgb


def _rays(cam_from_world: np.ndarray, k: np.ndarray, offsets=(0.0, 0.0)):
    """World-space directions (z = 1 in camera space) of the rays through every pixel (+ offset)."""
    ys, xs = np.meshgrid(np.arange(HEIGHT, dtype=float), np.arange(WIDTH, dtype=float), indexing="ij")
    pix = np.stack([xs.ravel() + offsets[0], ys.ravel() + offsets[1], np.ones(xs.size)], 1)
    cam_dirs = pix @ np.linalg.inv(k).T
    rot = cam_from_world[:3, :3]
    origin = -rot.T @ cam_from_world[:3, 3]
    return origin, cam_dirs @ rot          # rot.T applied to each row


def render_frame(prims, cam_from_world: np.ndarray, k: np.ndarray):
    """Ray-cast one frame: returns ``(rgb (H, W, 3), depth (H, W), world points (H*W, 3))``."""
    origin, dirs = _rays(cam_from_world, k)
    t, idx, normal = _cast(prims, origin, dirs)
    points = origin + dirs * t[:, None]
    rgb = np.zeros((HEIGHT * WIDTH, 3))
    for off in ((-0.25, -0.25), (0.25, -0.25), (-0.25, 0.25), (0.25, 0.25)):
        o, d = _rays(cam_from_world, k, off)
        ts, ids, ns = _cast(prims, o, d)
        rgb += _shade(prims, o + d * ts[:, None], ids, ns) / 4
    # camera-space rays have z = 1, so the ray parameter is the camera-z depth
    return rgb.reshape(HEIGHT, WIDTH, 3), t.reshape(HEIGHT, WIDTH), points


def write_demo_scene(root: str | Path) -> Path:
    """Generate every demo scene into ``root`` (Sintel layout, training split)."""
    root = Path(root)
    k = intrinsics()
    for name in SCENES:
        prims, cams = _scene(name)
        frames = [render_frame(prims, cam, k) for cam in cams]
        tr = root / "training"
        for i, ((rgb, depth, points), cam) in enumerate(zip(frames, cams), start=1):
            fname = f"frame_{i:04d}"
            write_png(tr / "clean" / name / f"{fname}.png", rgb)
            haze = (1 - np.exp(-depth / 40.0))[..., None]     # "final": depth haze, slight lens blur
            final = rgb * (1 - haze) + np.array([0.78, 0.80, 0.84]) * haze
            write_png(tr / "final" / name / f"{fname}.png", np.clip(cv2.GaussianBlur(final, (0, 0), 0.7), 0, 1))
            write_dpt(tr / "depth" / name / f"{fname}.dpt", depth.astype(np.float32))
            write_cam(tr / "camdata_left" / name / f"{fname}.cam", k, cam[:3])
            if i == len(frames):
                continue
            nxt = cams[i]
            cam_pts = points @ nxt[:3, :3].T + nxt[:3, 3]
            proj = cam_pts @ k.T
            uv = proj[:, :2] / proj[:, 2:3]
            grid = np.stack(np.meshgrid(np.arange(WIDTH), np.arange(HEIGHT), indexing="xy"), -1)
            flow = uv.reshape(HEIGHT, WIDTH, 2) - grid
            write_flo(tr / "flow" / name / f"{fname}.flo", flow.astype(np.float32))
            col, row = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
            inside = (col >= 0) & (col < WIDTH) & (row >= 0) & (row < HEIGHT) & (cam_pts[:, 2] > 0)
            next_depth = frames[i][1]
            seen = np.zeros(len(uv), bool)
            seen[inside] = next_depth[row[inside], col[inside]] >= cam_pts[inside, 2] * (1 - 2e-2)
            write_png(tr / "occlusions" / name / f"{fname}.png",
                      np.where(seen, 0, 255).astype(np.uint8).reshape(HEIGHT, WIDTH))
    return root


def cache_dir() -> Path:
    """The user cache folder (``$WEATHERGEN_CACHE`` or ``~/.cache/weathergen``)."""
    env = os.environ.get("WEATHERGEN_CACHE")
    if env:
        return Path(env)
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "weathergen"


def demo_root() -> Path:
    """Folder of the demo scene, generated on first use (atomically: a complete tree or none)."""
    root = cache_dir() / f"demo-scene-v{DEMO_VERSION}"
    if (root / ".complete").exists():
        return root
    root.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".demo-scene-", dir=root.parent))
    try:
        write_demo_scene(tmp)
        digest = hashlib.sha256()
        for p in (p for p in sorted(tmp.rglob("*")) if p.is_file()):
            digest.update(str(p.relative_to(tmp)).encode() + p.read_bytes())
        (tmp / ".complete").write_text(digest.hexdigest() + "\n")
        try:
            os.rename(tmp, root)
        except OSError:
            if not (root / ".complete").exists():   # someone else's half-made folder: replace it
                shutil.rmtree(root, ignore_errors=True)
                os.rename(tmp, root)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return root
