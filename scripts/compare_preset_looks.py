"""The look of the paper's presets: weathergen's sampling against the research code's, per seed.

Writes a small Sintel-format scene (``bamboo_1``, two frames: a ground plane 0.6 below the
camera, three boxes at depths 1.2-4.5, a back wall at 12; a camera that moves 0.3 forward and
0.1 right and turns by 1 degree; a z-up world as Sintel's), samples each preset's particles over
several seeds with weathergen (:func:`weathergen.engine.sample_particles`, as ``render --preset``
does) and, where a checkout of the research code is given, with the research code's own sampler
(``initialize_weather_split``, with the settings of its readme's commands and of the paper's
table), and prints per preset and side, each as the mean ± sd over the seeds:

- ``in view 1`` / ``in view 2``: particle centres each frame shows in front of the scene;
- ``depth``: camera-1 depth of the particles (mean, 10th, 50th and 90th percentile);
- ``footprint``: pixels of a particle's stamp whose alpha exceeds 1/20 (mean, median, 75th
  percentile; the research code's stamps as it stored them, weathergen's as it builds them);
- frame 1 drawn over the clean frame (float, no rounding): ``changed``, the share of pixels
  whose largest channel change exceeds 2/255; ``mean change`` (grey levels) over those pixels;
  ``specks``, their 8-connected regions.

The research code's particles are drawn by weathergen's renderer from the files its
``save_weatherfile`` writes, in ``--compat reference`` (which gives the research code's own
float frames to within 0.5/255, docs/render.md), so that only the sampling and the stamps
differ; weathergen's own particles as ``--compat`` says (default ``reference``). The
research code (https://github.com/cv-stuttgart/DistractingDownpour, GPL-3.0) is run unmodified
in a separate interpreter (``--research-python``, one with scipy, imageio and OpenCV); nothing
of it is part of weathergen. Run from the repository root::

    python scripts/compare_preset_looks.py [--research PATH --research-python PY] \\
        [--size 1024x436] [--seeds 10] [--research-seeds 5] [--compat reference] [--reuse]

(docs/render.md, "The look of the paper's presets", gives the figures and what they showed.)

The figures are recorded in docs/figures/bench.json and bench.md (``BENCH_FIGURES`` as for the
benchmarks); ``--json PATH`` also writes them as JSON.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from argparse import Namespace
from pathlib import Path

import cv2
import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))

from research_code import research_sintel  # noqa: E402

SCENE = "bamboo_1"     # a scene the research code's depth-scale table leaves as it is
#: The research code's generation arguments for each of our presets (its readme's commands and
#: the paper's table); ``sparks-research`` is its readme's colour, (255, 100, 70), no S jitter.
RESEARCH = {
    "snow": dict(flakesize_max=71, depth_decay=9, motion_y=0.2, rendering_method="additive",
                 transparency_scale=0.75, do_motionblur=False),
    "rain": dict(flakesize_max=51, depth_decay=9, motion_y=0.2, motion_random_scale=0.1,
                 motion_random_angle=4, rendering_method="additive", transparency_scale=0.75,
                 do_motionblur=True, motionblur_scale=0.15, motionblur_samples=20),
    "sparks": dict(flakesize_max=41, depth_decay=9, motion_y=-0.05, motion_random_scale=0.2,
                   motion_random_angle=60, flake_r=191, flake_g=79, flake_b=64, flake_random_h=15,
                   flake_random_s=0.1, flake_random_l=0.1, rendering_method="additive",
                   transparency_scale=1.5, do_motionblur=True, motionblur_scale=0.3,
                   motionblur_samples=10),
    "sparks-research": dict(flakesize_max=41, depth_decay=9, motion_y=-0.05,
                            motion_random_scale=0.2, motion_random_angle=60, flake_r=255,
                            flake_g=100, flake_b=70, flake_random_h=15, flake_random_l=0.1,
                            rendering_method="additive", transparency_scale=1.5,
                            do_motionblur=True, motionblur_scale=0.3, motionblur_samples=10),
    "fog": dict(flakesize_max=451, depth_decay=0.8, motion_y=0.0, flake_template_folder="dust",
                rendering_method="meshkin", transparency_scale=0.25, do_motionblur=False),
}
RESEARCH_DEFAULTS = dict(motion_x=0.0, motion_z=0.0, motion_random_scale=0.0,
                         motion_random_angle=0.0, flake_r=255, flake_g=255, flake_b=255,
                         flake_random_h=0.0, flake_random_s=0.0, flake_random_l=0.0,
                         flake_template_folder="particles", do_rotate=True, do_scale=True,
                         do_blur=True, do_transp=True, do_shape=True, motionblur_scale=0.025,
                         motionblur_samples=10, cpu_count=1)
#: weathergen's preset and overrides for each row.
OURS = {"snow": ("snow", {}), "rain": ("rain", {}), "sparks": ("sparks", {}),
        "sparks-research": ("sparks", {"color": "[255, 100, 70]", "saturation_jitter": "0"}),
        "fog": ("fog", {})}
CHANGED = 2 / 255        # a pixel counts as changed above this largest channel difference
ALPHA_EDGE = 1 / 20      # a stamp pixel counts towards the footprint above this alpha
#: The statistics, in the order printed: (key, label, digits).
STATS = (("view1", "in view 1", 0), ("view2", "in view 2", 0), ("depth_mean", "depth mean", 3),
         ("depth_p10", "depth p10", 3), ("depth_p50", "depth p50", 3),
         ("depth_p90", "depth p90", 3), ("foot_mean", "footprint mean (px)", 2),
         ("foot_p50", "footprint p50 (px)", 1), ("foot_p75", "footprint p75 (px)", 1),
         ("changed", "changed", 4), ("mean_change", "mean change (/255)", 3),
         ("specks", "specks", 1))


# -- the scene -----------------------------------------------------------------------------

def _rot_y(degrees: float) -> np.ndarray:
    a = math.radians(degrees)
    return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])


#: Camera 1 in Sintel's z-up world: x right, y down (world -z), z forward (world +y).
CAM1_FROM_WORLD = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])
#: Camera 2 in camera-1 coordinates: turned by 1 degree, its centre at (0.1, 0, 0.3).
CAM2_FROM_CAM1 = np.concatenate([_rot_y(1.0), -_rot_y(1.0) @ np.array([[0.1], [0], [0.3]])], 1)
#: Boxes in camera-1 coordinates (min corner, max corner), standing on the ground y = 1.6.
BOXES = (((-1.2, 0.1, 1.2), (-0.5, 0.6, 1.6)), ((0.4, -0.4, 2.0), (1.2, 0.6, 2.6)),
         ((-0.5, -0.2, 3.5), (0.3, 0.6, 4.5)))
GROUND, WALL = 0.6, 12.0


def scene_depth(k: np.ndarray, cam_from_cam1: np.ndarray, h: int, w: int) -> np.ndarray:
    """Camera depth of the scene (ground, boxes, wall) at each pixel. Shape: -> (H, W)."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    rays = np.stack([x, y, np.ones_like(x)], -1) @ np.linalg.inv(k).T     # camera axes, z = 1
    rot, t = cam_from_cam1[:, :3], cam_from_cam1[:, 3]
    origin, dirs = -rot.T @ t, rays @ rot                                   # camera-1 axes
    with np.errstate(divide="ignore", invalid="ignore"):
        best = np.where(dirs[..., 2] > 0, (WALL - origin[2]) / dirs[..., 2], np.inf)
        ground = (GROUND - origin[1]) / dirs[..., 1]
        best = np.where((dirs[..., 1] > 0) & (ground < best), ground, best)
        for lo, hi in BOXES:
            t0 = (np.array(lo) - origin) / dirs
            t1 = (np.array(hi) - origin) / dirs
            near = np.nanmax(np.minimum(t0, t1), -1)
            far = np.nanmin(np.maximum(t0, t1), -1)
            hit = (near <= far) & (near > 0) & (near < best)
            best = np.where(hit, near, best)
    return np.minimum(best, 1e3).astype(np.float32)                      # t along z = 1 rays


def write_scene(root: Path, h: int, w: int) -> None:
    """The Sintel-format tree of the module doc under ``root`` (training, clean pass)."""
    from weathergen.io.images import write_png
    from weathergen.io.sintel_formats import write_cam, write_dpt, write_flo

    k = np.array([[0.85 * w, 0, w / 2 - 0.5], [0, 0.85 * w, h / 2 - 0.5], [0, 0, 1]])
    rng = np.random.default_rng(5)
    cam1 = np.concatenate([CAM1_FROM_WORLD, np.zeros((3, 1))], 1)
    cam2 = np.concatenate([CAM2_FROM_CAM1[:, :3] @ CAM1_FROM_WORLD, CAM2_FROM_CAM1[:, 3:]], 1)
    y, x = np.mgrid[0:h, 0:w]
    for i, (cam, rel) in enumerate(((cam1, np.eye(3, 4)), (cam2, CAM2_FROM_CAM1)), 1):
        depth = scene_depth(k, rel, h, w)
        shade = 0.3 + 0.12 * np.sin(x / 9.0 + i) * np.cos(y / 13.0) + 0.1 / (1 + depth / 10)
        image = shade[..., None] + 0.05 * rng.random((h, w, 3))
        name = f"frame_{i:04d}"
        write_png(root / "training" / "clean" / SCENE / f"{name}.png", np.clip(image, 0, 1))
        write_dpt(root / "training" / "depth" / SCENE / f"{name}.dpt", depth)
        write_cam(root / "training" / "camdata_left" / SCENE / f"{name}.cam", k, cam)
        if i == 1:
            write_flo(root / "training" / "flow" / SCENE / f"{name}.flo",
                      np.zeros((h, w, 2), np.float32))


# -- the research code's side (run in its own interpreter) ----------------------------------

def research_worker(research: Path, tree: Path, out: Path, rows: list, seeds: int,
                    counts: dict) -> None:
    """Sample each row's particles with the research code over ``seeds`` seeds and save them
    with its ``save_weatherfile`` as ``out/ROW/seed_S/SCENE/frame_0001.npz``."""
    ds = research_sintel(research, tree)
    from weather_attack import utils, weather
    scene_data = [torch.as_tensor(np.asarray(s)).float()[None] for s in ds[0][4]]
    for row in rows:
        args = Namespace(**{**RESEARCH_DEFAULTS, **RESEARCH[row], "num_flakes": counts[row],
                            "flake_folder": str(research / "weather_attack" / "billboards")})
        flakes = weather.extract_flakes(args)
        for s in range(seeds):
            start = time.perf_counter()
            found = weather.initialize_weather_split(scene_data, args.num_flakes, args,
                                                     seed=1000 * s + 7, flake_array=flakes)
            target = out / row / f"seed_{s}" / SCENE
            target.mkdir(parents=True, exist_ok=True)
            utils.save_weatherfile(str(target / "frame_0001.npz"),
                                   tuple(t[:, :args.num_flakes] for t in found))
            print(f"research {row} seed {s}: {time.perf_counter() - start:.1f} s", flush=True)


# -- the statistics ------------------------------------------------------------------------

def image_stats(clean: np.ndarray, drawn: np.ndarray) -> dict:
    """changed share, mean change (/255) over changed pixels, specks. Shape: (H, W, 3) each."""
    diff = np.abs(drawn.astype(np.float64) - clean.astype(np.float64)).max(-1)
    mask = diff > CHANGED
    regions, _ = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    return {"changed": float(mask.mean()),
            "mean_change": float(255 * diff[mask].mean()) if mask.any() else 0.0,
            "specks": float(regions - 1)}


def placed_areas(stamps, seed: int = 0) -> np.ndarray:
    """Pixels above :data:`ALPHA_EDGE` of each stamp (a :class:`~weathergen.engine.stamps.
    StampSet`) as the splat places it at a random sub-pixel position: bilinearly between its
    values, ``1 / P`` pixel apart (P its phases; on its coarse grid for a coarse one).
    Shape: -> (E,)."""
    gen = torch.Generator().manual_seed(seed)
    frac = torch.rand(stamps.count, 2, generator=gen, dtype=torch.float64)
    out = np.zeros(stamps.count)
    keys = torch.stack((stamps.side, stamps.phases), 1)
    for side, phases in torch.unique(keys, dim=0).tolist():
        rows = torch.nonzero((keys == torch.tensor([side, phases])).all(1)).squeeze(1)
        n, half = phases * (side + 1) + 1, (side + 1) // 2
        grids = stamps.pixels[stamps.first[rows, None] + torch.arange(n * n)].view(-1, 1, n, n)
        offsets = torch.arange(-half - 1, half + 2, dtype=torch.float64)     # placed pixels
        where = (offsets[None, :, None] - frac[rows][:, None, :] + half) * phases  # (G, m, 2)
        norm = (2 * where / (n - 1) - 1).flip(-1)          # grid_sample wants (x, y)
        grid = torch.stack(torch.broadcast_tensors(norm[:, None, :, 0:1], norm[:, :, None, 1:2]),
                           -1).squeeze(-2)
        placed = torch.nn.functional.grid_sample(grids.double(), grid, align_corners=True)
        area = (placed > ALPHA_EDGE).flatten(1).sum(1).double()
        out[rows.numpy()] = (area * 4.0 ** stamps.coarse[rows]).numpy()
    return out


def particle_stats(pair, record, stamps) -> dict:
    """Per-record statistics of the particles themselves (see the module doc)."""
    from weathergen.engine import reference_transforms, visible_counts
    from weathergen.geometry import transform_points

    _, cam1, _ = reference_transforms(pair)
    depth = transform_points(cam1.cpu(), record.position.double().cpu())[:, 2].numpy()
    areas = placed_areas(stamps)
    v1, v2 = visible_counts(pair, record)
    return {"view1": float(v1), "view2": float(v2), "depth_mean": float(depth.mean()),
            "depth_p10": float(np.percentile(depth, 10)),
            "depth_p50": float(np.percentile(depth, 50)),
            "depth_p90": float(np.percentile(depth, 90)), "foot_mean": float(areas.mean()),
            "foot_p50": float(np.median(areas)), "foot_p75": float(np.percentile(areas, 75))}


def record_stats(pair, record, compat: str) -> dict:
    """Every statistic of one record drawn into frame 1 of ``pair``."""
    from weathergen.engine import render_pair
    from weathergen.engine.rendering.stamps import build, stored
    from weathergen.engine.weather.templates import load_templates
    from weathergen.engine.rendering.tracks import ParticleTable, RecordRows, fixed_looks

    record = record.for_compat(compat)
    if record.stamps is not None:
        stamps = stored(record.stamps)
    else:           # the stamps as the renderer builds them, every pixel on the image's grid
        lib = load_templates(record.settings.templates)
        looks = fixed_looks(ParticleTable.of([record], "cpu"), RecordRows.of([record], "cpu"),
                            lib.resolution)
        stamps = build(looks, lib, coarse_side=None)
    with torch.no_grad():
        drawn = render_pair(pair, record)
    clean = pair.image1.permute(1, 2, 0).numpy()
    return {**particle_stats(pair, record, stamps),
            **image_stats(clean, drawn.image1[0].permute(1, 2, 0).numpy())}


def ours(pair, row: str, seeds: int, compat: str) -> list:
    """weathergen's statistics of a row over ``seeds`` seeds (the render's own seeds 0..)."""
    from weathergen.engine import load_preset, sample_particles
    name, overrides = OURS[row]
    preset = load_preset(name, overrides)
    return [record_stats(pair, sample_particles(pair, preset, seed), compat)
            for seed in range(seeds)]


def theirs(pair, folder: Path, row: str, seeds: int) -> list:
    """The research code's statistics of a row from the files its sampler left in ``folder``."""
    from weathergen.engine import load_preset
    from weathergen.engine.sampling.published import published_particles
    from weathergen.io.published_weather import published_file, read_published_weather

    preset = load_preset(OURS[row][0])
    return [record_stats(pair, published_particles(read_published_weather(
        published_file(folder / row / f"seed_{s}", SCENE, 1)), pair, preset), "reference")
        for s in range(seeds)]


def summary(draws: list) -> dict:
    """Mean and sd (over the draws; sd with one degree of freedom) of every statistic."""
    out = {}
    for key, _, _ in STATS:
        values = np.array([d[key] for d in draws])
        out[key] = {"mean": float(values.mean()),
                    "sd": float(values.std(ddof=1)) if len(values) > 1 else 0.0,
                    "n": len(values)}
    return out


def print_table(row: str, ours_: dict, theirs_: dict | None) -> None:
    print(f"\n{row}")
    head = f"  {'statistic':22s} {'weathergen':>22s}"
    print(head + (f" {'research code':>22s} {'ratio':>6s} {'z':>6s}" if theirs_ else ""))
    for key, label, digits in STATS:
        o = ours_[key]
        line = f"  {label:22s} {o['mean']:>12.{digits}f} ± {o['sd']:<7.{digits}f}"
        if theirs_:
            t = theirs_[key]
            ratio = o["mean"] / t["mean"] if t["mean"] else float("nan")
            z = (o["mean"] - t["mean"]) / t["sd"] if t["sd"] else float("nan")
            line += f" {t['mean']:>12.{digits}f} ± {t['sd']:<7.{digits}f} {ratio:6.3f} {z:6.2f}"
        print(line)


# -- main ----------------------------------------------------------------------------------

def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--research", type=Path,
                        help="a checkout of cv-stuttgart/DistractingDownpour (omitted: "
                             "weathergen's side alone)")
    parser.add_argument("--research-python", default=sys.executable,
                        help="the interpreter that runs the research code")
    parser.add_argument("--reuse", action="store_true",
                        help="read the research code's particles an earlier run left in --out "
                             "(it is not run again)")
    parser.add_argument("--research-commit", default=None,
                        help="the research code's commit (default: asked of its git checkout)")
    parser.add_argument("--research-seeds", type=int, default=5)
    parser.add_argument("--seeds", type=int, default=10, help="weathergen's seeds")
    parser.add_argument("--size", default="1024x436", help="frame size WxH")
    parser.add_argument("--rows", default="snow,rain,sparks,sparks-research,fog")
    parser.add_argument("--compat", default="reference", choices=("paper", "reference"),
                        help="how weathergen samples and draws its particles")
    parser.add_argument("--out", type=Path, default=Path("out/preset-looks"))
    parser.add_argument("--json", type=Path, help="also write the figures here")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    return parser.parse_args(argv)


def research_commit(args) -> str:
    """``--research-commit``, else the research checkout's HEAD, else ``unknown``."""
    if args.research_commit or args.research is None:
        return args.research_commit or "unknown"
    found = subprocess.run(["git", "-C", str(args.research), "rev-parse", "HEAD"],
                           capture_output=True, text=True)
    return found.stdout.strip() if found.returncode == 0 else "unknown"


def run_research(args, rows: list, counts: dict) -> None:
    """The research code's sampler, in its own interpreter (this script with ``--worker``)."""
    command = [args.research_python, str(Path(__file__).resolve()), "--worker",
               "--research", str(args.research.resolve()), "--out", str(args.out.resolve()),
               "--research-seeds", str(args.research_seeds), "--size", args.size,
               "--rows", ",".join(f"{r}:{counts[r]}" for r in rows)]
    subprocess.run(command, check=True, env={**os.environ, "OMP_NUM_THREADS": "1"})


def main(argv=None) -> dict:
    args = parse_args(argv)
    w, h = (int(v) for v in args.size.lower().split("x"))
    if args.worker:
        rows = dict(r.split(":") for r in args.rows.split(","))
        research_worker(args.research, args.out / "sintel", args.out / "research", list(rows),
                        args.research_seeds, {r: int(c) for r, c in rows.items()})
        return {}
    sys.path.insert(0, str(ROOT))
    from weathergen.datasets import open_dataset
    from weathergen.engine import load_preset
    from weathergen.engine.weather.presets import frame_scaling

    rows = [r.strip() for r in args.rows.split(",") if r.strip()]
    write_scene(args.out / "sintel", h, w)
    counts = {r: frame_scaling(load_preset(OURS[r][0]), h, w).count for r in rows}
    research = args.research is not None or args.reuse
    if args.research is not None and not args.reuse:
        run_research(args, rows, counts)
    ds = open_dataset("sintel", args.out / "sintel")
    pair = ds.load(ds.pairs()[0])
    commit = research_commit(args) if research else None
    print(f"scene {w}x{h}, weathergen: {args.seeds} seeds, --compat {args.compat}; research code: "
          f"{args.research_seeds if research else 0} seeds (commit {commit}); mean ± sd over "
          "the seeds")
    figures = {"size": [w, h], "compat": args.compat, "research_commit": commit,
               "seeds": args.seeds, "research_seeds": args.research_seeds if research else 0,
               "rows": {}}
    for row in rows:
        o = summary(ours(pair, row, args.seeds, args.compat))
        t = summary(theirs(pair, args.out / "research", row, args.research_seeds)) \
            if research else None
        figures["rows"][row] = {"weathergen": o, "research": t, "count": counts[row]}
        print_table(row, o, t)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(figures, indent=1) + "\n")
    return figures


def recorded() -> int:
    """main(), its printout recorded as a section of the figures file (speed/figures.py)."""
    sys.path.insert(0, str(ROOT / "speed"))
    import figures
    return figures.record(lambda: (main(), None)[1])


if __name__ == "__main__":
    sys.exit(recorded())
