"""Synthetic frame pairs for the engine tests: planes at known depth seen by simple cameras."""

from __future__ import annotations

import math

import torch

from weathergen.framepair import FramePair, PairId


def rotation(roll_deg: float = 0.0, pitch_deg: float = 0.0, yaw_deg: float = 0.0) -> torch.Tensor:
    """Camera-from-world rotation for a camera rolled about z, pitched about x, yawed about y."""
    r, p, y = (math.radians(a) for a in (roll_deg, pitch_deg, yaw_deg))
    rz = torch.tensor([[math.cos(r), -math.sin(r), 0], [math.sin(r), math.cos(r), 0], [0, 0, 1]])
    rx = torch.tensor([[1, 0, 0], [0, math.cos(p), -math.sin(p)], [0, math.sin(p), math.cos(p)]])
    ry = torch.tensor([[math.cos(y), 0, math.sin(y)], [0, 1, 0], [-math.sin(y), 0, math.cos(y)]])
    return (rz @ rx @ ry).double()


def pose(rot: torch.Tensor, centre=(0.0, 0.0, 0.0)) -> torch.Tensor:
    """cam_from_world for a camera with rotation ``rot`` (cam_from_world) at world ``centre``."""
    out = torch.eye(4, dtype=torch.float64)
    out[:3, :3] = rot
    out[:3, 3] = -rot @ torch.tensor(centre, dtype=torch.float64)
    return out


def plane_pair(height: int = 48, width: int = 64, depth: float = 4.0, *, world: bool = True,
               cam1_from_world: torch.Tensor | None = None,
               cam2_from_world: torch.Tensor | None = None, near_block: bool = False,
               dtype=torch.float32, seed: int = 0) -> FramePair:
    """A textured fronto-parallel plane at ``depth`` (optionally a near block at depth 1 in the
    left third); identity cameras unless given."""
    g = torch.Generator().manual_seed(seed)
    img1 = (0.2 + 0.6 * torch.rand(3, height, width, generator=g)).to(dtype)
    img2 = (0.2 + 0.6 * torch.rand(3, height, width, generator=g)).to(dtype)
    d = torch.full((1, height, width), depth, dtype=dtype)
    if near_block:
        d[..., : width // 3] = 1.0
    f = 0.8 * width
    k = torch.tensor([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]],
                     dtype=torch.float64)
    c1 = cam1_from_world if cam1_from_world is not None else torch.eye(4, dtype=torch.float64)
    c2 = cam2_from_world if cam2_from_world is not None else torch.eye(4, dtype=torch.float64)
    rel = c2 @ torch.linalg.inv(c1)
    return FramePair(id=PairId("synthetic", "test", "plane", 1), image1=img1, image2=img2,
                     depth1=d, depth2=d.clone(), intrinsics=k, cam2_from_cam1=rel,
                     cam1_from_world=c1 if world else None, cam2_from_world=c2 if world else None)


#: Sintel's frame size and focal length (pixels).
SINTEL_SIZE = (436, 1024)
SINTEL_FOCAL = 1120.0


def bench_scene() -> FramePair:
    """The benchmarks' Sintel-size scene (1024 x 436): a tilted plane at 6 with a near block, its
    right part (columns from 600) at depth 2, and a camera that turns and moves a little."""
    cam1 = pose(rotation(roll_deg=3, pitch_deg=-5))
    cam2 = pose(rotation(roll_deg=3, pitch_deg=-4, yaw_deg=1), centre=(0.05, 0.0, 0.1))
    pair = plane_pair(436, 1024, depth=6.0, near_block=True, cam1_from_world=cam1,
                      cam2_from_world=cam2)
    pair.depth1[..., :, 600:] = 2.0
    pair.depth2[..., :, 600:] = 2.0
    return pair


def _texture(a: torch.Tensor, b: torch.Tensor, seed: int) -> torch.Tensor:
    """A smooth texture in [0.15, 0.65] over surface coordinates a (W,) along the columns and
    b (H,) along the rows (scene units): a checker of quarter-unit squares under a few random
    sinusoids. Shape: -> (H, W)."""
    g = torch.Generator().manual_seed(seed)
    out = torch.full((b.numel(), a.numel()), 0.4, dtype=torch.float64)
    for _ in range(6):
        fa, fb = (2 + 12 * torch.rand(2, generator=g, dtype=torch.float64)).tolist()
        pa, pb = (2 * math.pi * torch.rand(2, generator=g, dtype=torch.float64)).tolist()
        out += 0.035 * torch.sin(fb * b + pb)[:, None] * torch.sin(fa * a + pa)[None, :]
    checker = torch.remainder(torch.floor(4 * b)[:, None] + torch.floor(4 * a)[None, :], 2)
    return (out + 0.06 * (checker - 0.5)).clamp(0.15, 0.65)


def wall_scene(*, forward: float = 0.0, plane_depth: float = 6.0, wall_depth: float = 1.2,
               wall_columns: int = 300, size: tuple = SINTEL_SIZE, focal: float = SINTEL_FOCAL,
               dtype=torch.float32) -> FramePair:
    """A Sintel-size pair: a textured fronto-parallel plane at ``plane_depth`` and a textured
    near wall at ``wall_depth`` covering the image columns left of ``wall_columns`` in frame 1
    (the wall ends at world x = (wall_columns - cx) / f * wall_depth).

    Camera 1 is the world (identity pose, y down); camera 2 moved ``forward`` scene units along
    the view axis (0: a static camera). Both frames are ray-cast from their own camera, so the
    texture, the wall's edge and the depth move as the camera does.
    """
    height, width = size
    cx, cy = (width - 1) / 2, (height - 1) / 2
    k = torch.tensor([[focal, 0, cx], [0, focal, cy], [0, 0, 1]], dtype=torch.float64)
    wall_x = (wall_columns - cx) / focal * wall_depth
    # ray directions with z = 1: x along the columns, y along the rows
    rx = (torch.arange(width, dtype=torch.float64) - cx) / focal
    ry = (torch.arange(height, dtype=torch.float64) - cy) / focal

    def cast(z0: float):
        t_wall, t_plane = wall_depth - z0, plane_depth - z0
        on_wall = ((t_wall > 0) & (t_wall * rx < wall_x))[None, :].expand(height, width)
        t = torch.where(on_wall, t_wall, t_plane)
        img = torch.stack([torch.where(on_wall, 0.8 * _texture(3 * t_wall * rx, 3 * t_wall * ry, 4 + c),
                                       _texture(t_plane * rx, t_plane * ry, 1 + c))
                           for c in range(3)])
        return img.to(dtype), t[None].to(dtype)

    img1, d1 = cast(0.0)
    img2, d2 = cast(forward)
    c1 = torch.eye(4, dtype=torch.float64)
    c2 = pose(torch.eye(3, dtype=torch.float64), (0.0, 0.0, forward))
    return FramePair(id=PairId("synthetic", "test", "wall", 1), image1=img1, image2=img2,
                     depth1=d1, depth2=d2, intrinsics=k, cam2_from_cam1=c2 @ torch.linalg.inv(c1),
                     cam1_from_world=c1, cam2_from_world=c2)


def forward_scene(forward: float = 0.5, **kwargs) -> FramePair:
    """:func:`wall_scene` with camera 2 moved ``forward`` scene units along the view axis."""
    return wall_scene(forward=forward, **kwargs)


def write_sintel_scene(root, scene: str, pair: FramePair) -> None:
    """Write ``pair`` as frames 1 and 2 of a Sintel training scene below ``root`` (clean pass,
    depth, cameras: world-to-camera extrinsics from the pair's poses)."""
    from pathlib import Path

    from weathergen.io.images import write_png
    from weathergen.io.sintel_formats import write_cam, write_dpt

    root = Path(root) / "training"
    k = pair.intrinsics.double().numpy()
    for i, (img, depth, cam) in enumerate(((pair.image1, pair.depth1, pair.cam1_from_world),
                                           (pair.image2, pair.depth2, pair.cam2_from_world)), 1):
        name = f"frame_{i:04d}"
        write_png(root / "clean" / scene / f"{name}.png", img.permute(1, 2, 0).double().numpy())
        write_dpt(root / "depth" / scene / f"{name}.dpt", depth[0].float().numpy())
        write_cam(root / "camdata_left" / scene / f"{name}.cam", k, cam.double().numpy()[:3])


def write_motion_scenes(root, **small) -> None:
    """A Sintel tree of three scenes for the frame-2 note: two whose camera drives one unit into
    the sampling box (``ahead_a``, ``ahead_b``) and a still one (``still``)."""
    write_sintel_scene(root, "ahead_a", wall_scene(forward=1.0, **small))
    write_sintel_scene(root, "ahead_b", wall_scene(forward=1.0, plane_depth=8.0, **small))
    write_sintel_scene(root, "still", wall_scene(**small))


def assert_few_in_frame2_marked(out) -> None:
    """The manifest of a run over :func:`write_motion_scenes` marks the two driving scenes'
    pairs ``few_in_frame2`` and not the still one, consistently with their visible counts."""
    import json
    from pathlib import Path

    pairs = json.loads((Path(out) / "manifest.json").read_text())["pairs"]
    marked = {key.split(":")[2]: entry["few_in_frame2"] for key, entry in pairs.items()}
    assert marked == {"ahead_a": True, "ahead_b": True, "still": False}, pairs
    for entry in pairs.values():
        v1, v2 = entry["visible"]
        assert entry["few_in_frame2"] == (v2 < 0.5 * v1)


def count_operations(fn) -> int:
    """The tensor operations ``fn()`` dispatches (every one: kernel launches, views, host-side
    bookkeeping), counted on its second call (the first builds cached template atlases)."""
    from torch.utils._python_dispatch import TorchDispatchMode

    class Counter(TorchDispatchMode):
        def __init__(self):
            super().__init__()
            self.ops = 0

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            self.ops += 1
            return func(*args, **(kwargs or {}))

    fn()
    counter = Counter()
    with counter:
        fn()
    return counter.ops


#: Wisps of haze as particles: the billboard fog the field presets drew before they became
#: atmospheres (4 m `haze` clouds, alpha blended, θ 0.15, from 1 to 25 m, 0.03 per m³), with
#: no atmosphere of their own. Overrides of any field preset (``load_preset("fog-moderate",
#: HAZE_WISPS)``), or of a layer (:func:`wisps`).
HAZE_WISPS = {"density": "0.03", "diameter": "4.0", "diameter_jitter": "0.3", "templates": "haze",
              "blend": "alpha", "transparency": "0.15", "fall_speed": "0", "exposure": "0",
              "blur_samples": "1", "near": "1.0", "far": "25.0", "fade": "0.4",
              "aperture": "0", "focus": "5.0", "depth_softness": "0.2", "tile": "10.0",
              "visibility": "0", "rain_rate": "0", "snow_rate": "0"}


def wisps(layer: str, density: float = 0.03, atmosphere: bool = False) -> dict:
    """:data:`HAZE_WISPS` for layer ``layer`` of a combined preset, at ``density`` per m³
    (keeping the layer's own atmosphere with ``atmosphere``)."""
    values = {**HAZE_WISPS, "density": str(density)}
    if atmosphere:
        for key in ("visibility", "rain_rate", "snow_rate"):
            values.pop(key)
    return {f"{layer}.{k}": v for k, v in values.items()}


def column_scene(size: tuple = (218, 512), *, column_depth: float = 0.7, far: float = 5.0,
                 floor: float = 0.25, columns: tuple = (0.3, 0.45), focal: float = 560.0,
                 dtype=torch.float32) -> FramePair:
    """A corridor as a real indoor pair shows it: a textured back wall at ``far``, a floor
    ``floor`` scene units below the camera receding towards it, and a near column at
    ``column_depth`` whose face spans the image columns ``columns`` (fractions of the width),
    in front of both. Both frames from identity cameras (the column's edges are vertical depth
    edges from 0.7 to 5 units; the floor crosses every depth in between)."""
    height, width = size
    cx, cy = (width - 1) / 2, (height - 1) / 2
    k = torch.tensor([[focal, 0, cx], [0, focal, cy], [0, 0, 1]], dtype=torch.float64)
    rx = ((torch.arange(width, dtype=torch.float64) - cx) / focal)[None, :].expand(height, width)
    ry = ((torch.arange(height, dtype=torch.float64) - cy) / focal)[:, None].expand(height, width)
    depth = torch.full((height, width), far, dtype=torch.float64)
    on_floor = ry * far > floor
    depth = torch.where(on_floor, floor / ry.clamp(min=1e-9), depth)
    u = torch.arange(width, dtype=torch.float64)[None, :].expand(height, width)
    on_column = (u >= columns[0] * width) & (u < columns[1] * width)
    depth = torch.where(on_column, torch.full_like(depth, column_depth), depth)
    a, b = depth * rx, depth * ry                      # surface coordinates, scene units
    checker = torch.remainder(torch.floor(4 * a) + torch.floor(4 * b), 2)
    texture = torch.stack([0.4 + 0.08 * (checker - 0.5) + 0.05 * torch.sin((5 + 2 * c) * a)
                           * torch.sin((3 + c) * b + c) for c in range(3)])
    texture = torch.where(on_column[None], 0.8 * texture, texture)
    d = depth[None].to(dtype)
    eye = torch.eye(4, dtype=torch.float64)
    return FramePair(id=PairId("synthetic", "test", "column", 1), image1=texture.to(dtype),
                     image2=texture.to(dtype), depth1=d, depth2=d.clone(), intrinsics=k,
                     cam2_from_cam1=eye, cam1_from_world=eye, cam2_from_world=eye.clone())
