"""weathergen against the paper's research code on the research code's own particle files.

Writes a small Sintel-format tree (two scenes: ``alley_1``, which the research code scales by 2
and whose camera translation it zeroes, and ``bamboo_1``, which it leaves as it is; a textured
plane at depth 6, a near wall at 1.2, a near box at 0.8 and a post at 2.0, the same in both
frames; a camera that turns by 1.5 degrees and moves 0.3 right and 0.4 forward), runs the
research code on it (its Sintel reader, its generator and its renderer, with the settings of its
readme's snow, rain, sparks and fog commands and of the paper's table's alpha-blended white and
red sparks, alpha-white and alpha-red; fewer particles), saves each pair's particles with its
``save_weatherfile`` in the published layout (``SET/SCENE/frame_0001.npz``) and its float
frames, then reads every file with weathergen (:mod:`weathergen.io.published_weather`), draws it
in the research code's frame and scaling (``--scene-scales research``, camera translation zeroed
in the scaled scenes) with the preset of the same name, as ``--compat reference`` draws it
(α-blended motion blur blended one sample after another, the scene depth read half a pixel up and
left; ``--depth-shift 0``: at the pixel), and prints per frame the largest and the mean absolute
difference between the two renders (grey levels of 255), overall and within 2 pixels of a depth
step.

Nothing of the research code is part of weathergen; this script imports it from the given folder
(https://github.com/cv-stuttgart/DistractingDownpour, GPL-3.0), unmodified. It needs ``scipy``,
``imageio`` and ``Pillow`` besides weathergen's dependencies; ``torchvision``, which the research
code imports but does not use here, is stood in for. Run it from the repository root::

    python scripts/compare_published_weather.py --research PATH/TO/DistractingDownpour \\
        --out out/published-comparison [--particles 400]

``--compare-only`` compares again what an earlier run left in ``--out`` (the research code is
not run; ``--research`` is not needed).
"""

from __future__ import annotations

import argparse
import math
import sys
from argparse import Namespace
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

from research_code import research_sintel  # noqa: E402

from weathergen.datasets import load_scene_scales, open_dataset  # noqa: E402
from weathergen.engine import load_preset, render_pair  # noqa: E402
from weathergen.engine.sampling.published import published_particles  # noqa: E402
from weathergen.io.images import write_png  # noqa: E402
from weathergen.io.published_weather import published_file, read_published_weather  # noqa: E402
from weathergen.io.sintel_formats import write_cam, write_dpt, write_flo  # noqa: E402

H, W = 160, 320
SCENES = ("alley_1", "bamboo_1")
#: The research code's readme commands, generation and rendering arguments (fog: blended as the
#: paper's table says, alpha / "meshkin").
CONFIGS = {
    "snow": dict(num_flakes=3000, flakesize_max=71, depth_decay=9, motion_y=0.2,
                 flake_template_folder="particles", rendering_method="additive",
                 transparency_scale=0.75, do_motionblur=False),
    "rain": dict(num_flakes=3000, flakesize_max=51, depth_decay=9, motion_y=0.2,
                 motion_random_scale=0.1, motion_random_angle=4, flake_template_folder="particles",
                 rendering_method="additive", transparency_scale=0.75, do_motionblur=True,
                 motionblur_scale=0.15, motionblur_samples=20),
    "sparks": dict(num_flakes=3000, flakesize_max=41, depth_decay=9, motion_y=-0.05,
                   motion_random_scale=0.2, motion_random_angle=60,
                   flake_template_folder="particles", flake_r=255, flake_g=100, flake_b=70,
                   flake_random_h=15, flake_random_l=0.1, rendering_method="additive",
                   transparency_scale=1.5, do_motionblur=True, motionblur_scale=0.3,
                   motionblur_samples=10),
    "alpha-white": dict(num_flakes=3000, flakesize_max=41, depth_decay=9, motion_y=-0.05,
                        motion_random_scale=0.2, motion_random_angle=60,
                        flake_template_folder="particles", rendering_method="meshkin",
                        transparency_scale=1.5, do_motionblur=True, motionblur_scale=0.3,
                        motionblur_samples=10),
    "alpha-red": dict(num_flakes=3000, flakesize_max=41, depth_decay=9, motion_y=-0.05,
                      motion_random_scale=0.2, motion_random_angle=60,
                      flake_template_folder="particles", flake_r=191, flake_g=79, flake_b=64,
                      flake_random_h=15, flake_random_s=0.1, flake_random_l=0.1,
                      rendering_method="meshkin", transparency_scale=1.5, do_motionblur=True,
                      motionblur_scale=0.3, motionblur_samples=10),
    "fog": dict(num_flakes=60, flakesize_max=451, depth_decay=0.8, motion_y=0.0,
                flake_template_folder="dust", rendering_method="meshkin",
                transparency_scale=0.25, do_motionblur=False),
}
DEFAULTS = dict(motion_x=0.0, motion_z=0.0, motion_random_scale=0.0, motion_random_angle=0.0,
                flake_r=255, flake_g=255, flake_b=255, flake_random_h=0.0, flake_random_s=0.0,
                flake_random_l=0.0, do_rotate=True, do_scale=True, do_blur=True, do_transp=True,
                do_shape=True, constant_transparency=0, depth_check=True,
                depth_check_differentiable=False, motionblur_scale=0.025, motionblur_samples=10,
                recolor=False, cpu_count=1)


def write_tree(root: Path) -> None:
    """The Sintel-format tree described in the module doc."""
    rng = np.random.default_rng(3)
    k = np.array([[300.0, 0, W / 2 - 0.5], [0, 300.0, H / 2 - 0.5], [0, 0, 1]])
    depth = np.full((H, W), 6.0, np.float32)
    depth[:, : int(0.3 * W)] = 1.2
    depth[45:115, 150:215] = 0.8            # a near box: its top and left edges face the plane
    depth[:, 250:262] = 2.0                 # a post
    a = math.radians(1.5)
    turn = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    y, x = np.mgrid[0:H, 0:W]
    for scene in SCENES:
        for i, (rot, move) in enumerate(((np.eye(3), np.zeros(3)), (turn, np.array([-0.3, 0, -0.4]))), 1):
            name = f"frame_{i:04d}"
            image = 0.35 + 0.15 * (np.sin(x / 7.0) * np.cos(y / 11.0))[..., None] \
                + 0.08 * rng.random((H, W, 3))
            write_png(root / "training" / "clean" / scene / f"{name}.png", np.clip(image, 0, 1))
            write_dpt(root / "training" / "depth" / scene / f"{name}.dpt", depth)
            write_cam(root / "training" / "camdata_left" / scene / f"{name}.cam", k,
                      np.concatenate([rot, move[:, None]], axis=1))
            if i == 1:
                write_flo(root / "training" / "flow" / scene / f"{name}.flo",
                          np.zeros((H, W, 2), np.float32))


def run_research(research: Path, tree: Path, out: Path, count: int, sets) -> None:
    """The research code's reader, generator, ``save_weatherfile`` and renderer on the tree."""
    ds = research_sintel(research, tree)
    from weather_attack import utils, weather
    from weather_attack.render import render
    for name in sets:
        config = CONFIGS[name]
        args = Namespace(**{**DEFAULTS, **config,
                            "flake_folder": str(research / "weather_attack" / "billboards")})
        if name != "fog":          # (fog keeps its 60 clouds)
            args.num_flakes = count
        flakes = weather.extract_flakes(args)
        for index in range(len(ds)):
            img1, img2, _, _, scene_data, extra = ds[index]
            scene, frame = extra[2], extra[4]
            scene_data = [torch.as_tensor(np.asarray(s)).float()[None] for s in scene_data]
            found = weather.initialize_weather_split(scene_data, args.num_flakes, args,
                                                     seed=1000 * index + 7, flake_array=flakes)
            found = tuple(t[:, :args.num_flakes] for t in found)
            target = out / name / scene
            target.mkdir(parents=True, exist_ok=True)
            utils.save_weatherfile(str(target / f"frame_{frame + 1:04d}.npz"), found)
            with torch.no_grad():
                frames = render(img1[None] / 255.0, img2[None] / 255.0, scene_data, list(found), args)
            for k, image in enumerate(frames, 1):
                np.save(target / f"frame_{k}_{frame + 1:04d}.npy", image[0].permute(1, 2, 0).numpy())


def near_steps(depth: np.ndarray, reach: int = 2) -> np.ndarray:
    """The pixels within ``reach`` pixels of a depth step (neighbours more than 10 % apart)."""
    step = np.zeros(depth.shape, bool)
    for axis in (0, 1):
        a, b = np.moveaxis(depth, axis, 0)[:-1], np.moveaxis(depth, axis, 0)[1:]
        jump = np.abs(a - b) > 0.1 * np.minimum(a, b)
        np.moveaxis(step, axis, 0)[:-1] |= jump
        np.moveaxis(step, axis, 0)[1:] |= jump
    grown = step.copy()
    for dy in range(-reach, reach + 1):
        for dx in range(-reach, reach + 1):
            grown |= np.roll(step, (dy, dx), (0, 1))
    return grown


def compare(tree: Path, out: Path, sets, depth_shift: float | None = None) -> None:
    """weathergen's render of every file against the research code's, per frame (with
    ``depth_shift``: the scene depth read there rather than where ``--compat reference`` reads
    it)."""
    ds = open_dataset("sintel", tree, scene_scales=load_scene_scales("research"),
                      camera_translation="unscaled")
    print("set     scene     frame  max |diff| (/255)  mean |diff| (/255)  pixels > 0.5/255  "
          "max within 2 px of a depth step")
    for name in sets:
        preset = load_preset(name)
        for ref in ds.pairs():
            pair = ds.load(ref)
            particles = published_particles(read_published_weather(
                published_file(out / name, ref.id.scene, ref.id.frame)), pair, preset) \
                .for_compat("reference")
            if depth_shift is not None:
                particles = particles.replace(settings=particles.settings.replace(
                    depth_shift=depth_shift))
            with torch.no_grad():
                ours = render_pair(pair, particles)
            for k, image, depth in ((1, ours.image1, pair.depth1), (2, ours.image2, pair.depth2)):
                theirs = np.load(out / name / ref.id.scene / f"frame_{k}_{ref.id.frame:04d}.npy")
                d = np.abs(image[0].permute(1, 2, 0).double().numpy() - theirs).max(-1) * 255
                edge = d[near_steps(depth[0].numpy())]
                print(f"{name:7s} {ref.id.scene:9s} {k:5d}  {d.max():17.3f}  {d.mean():18.5f}  "
                      f"{100 * (d > 0.5).mean():14.3f} %  {edge.max():17.3f}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--research", type=Path,
                        help="a checkout of cv-stuttgart/DistractingDownpour")
    parser.add_argument("--compare-only", action="store_true",
                        help="compare the files and frames an earlier run left in --out")
    parser.add_argument("--out", type=Path, default=Path("out/published-comparison"))
    parser.add_argument("--particles", type=int, default=400,
                        help="particles per pair of snow, rain and sparks (fog: its 60)")
    parser.add_argument("--depth-shift", type=float, default=None,
                        help="read the scene depth this many pixels up and left (default: as "
                             "--compat reference reads it, 0.5; 0: weathergen's own convention)")
    parser.add_argument("--sets", default=",".join(CONFIGS),
                        help=f"which of {', '.join(CONFIGS)} (comma-separated; default all)")
    args = parser.parse_args()
    sets = [s.strip() for s in args.sets.split(",") if s.strip()]
    tree, folder = args.out / "sintel", args.out / "sets"
    if not args.compare_only:
        if args.research is None:
            parser.error("--research is required (or --compare-only)")
        write_tree(tree)
        run_research(args.research.resolve(), tree, folder, args.particles, sets)
    compare(tree, folder, sets, args.depth_shift)


if __name__ == "__main__":
    main()
