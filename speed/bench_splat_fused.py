"""Probe: would a fused splat kernel beat the eager one on the CPU? The splat's forward pass of
sparks and rain (3000 particles, the Sintel-size bench scene, one thread, CPU time) in ns per
pixel-sample (patch pixel of a blur sample), three ways over the same chunks of the same plan:

- ``eager``: the render core's own forward (``engine/rendering/splat.py``);
- ``compiled``: each chunk's gathers, interpolation, visibility and weights as one function
  compiled by ``torch.compile`` (Inductor), the scatter-add left eager (``--compile``; compiling
  takes about a minute);
- ``warp``: the same per 2 x 2 block as one NVIDIA Warp kernel (``pip install warp-lang``; a
  thread per block, additions in the kernel), skipped where Warp is not installed.

Each is checked against the eager sums (max difference printed). Measured figures and the
conclusion are in docs/engine.md ("Benchmark").

    python speed/bench_splat_fused.py [--compile] [--presets sparks rain]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

import torch  # noqa: E402


def chunk_terms(pixels, scene, per, sample, at, stride, phases, pix0, pix1, channels: int):
    """One chunk's flat sum indices and weighted terms (what ``_Blocks`` and ``_Splat.forward``
    compute), written as one function for ``torch.compile``. Shape: block arrays (n,) ->
    (4 n,), (channels, 4 n)."""
    fu, fv, bz, be = per[0][sample], per[1][sample], per[2][sample], per[3][sample]
    j = torch.arange(2, device=at.device).view(2, 1, 1)
    i = torch.arange(2, device=at.device).view(1, 2, 1)
    base = at + j * phases + stride * (i * phases)
    n00, n01 = pixels[base], pixels[base + 1]
    n10, n11 = pixels[base + stride], pixels[base + stride + 1]
    top = n01 + fu * (n00 - n01)
    bottom = n11 + fu * (n10 - n11)
    patch = bottom + fv * (top - bottom)
    pix = torch.where(i == 0, pix0, pix1) + j
    e = torch.clamp(bz - be * scene[pix], -40.0, 40.0)
    w = patch / (1.0 + torch.exp(e))
    terms = w.unsqueeze(0) * per[4:4 + channels][:, sample].view(channels, 1, 1, -1)
    return pix.reshape(-1), terms.reshape(channels, -1)


def block_arrays(rows, row, lo, hi, whole):
    """Per block of a chunk: its sample, top-left stamp index, stride, P and pixel-row starts."""
    sample, at, pix0, pix1, stride = (x.index_select(0, row) for x in rows[:5])
    two_blocks = torch.arange(2 * lo, 2 * hi, 2)
    phases = torch.ones_like(at) if whole else rows[5].index_select(0, row)
    return sample, at + two_blocks * phases, stride, phases, pix0 + two_blocks, pix1 + two_blocks


def warp_kernel():
    """The Warp kernel (or None without Warp)."""
    try:
        import warp as wp
    except ImportError:
        return None, None
    wp.config.quiet = True
    wp.config.mode = "release"
    wp.init()

    @wp.kernel
    def splat_blocks(sample: wp.array(dtype=wp.int64), at: wp.array(dtype=wp.int64),
                     stride: wp.array(dtype=wp.int64), phases: wp.array(dtype=wp.int64),
                     pix0: wp.array(dtype=wp.int64), pix1: wp.array(dtype=wp.int64),
                     per: wp.array2d(dtype=wp.float32), pixels: wp.array(dtype=wp.float32),
                     scene: wp.array(dtype=wp.float32), channels: int,
                     acc: wp.array2d(dtype=wp.float32)):
        t = wp.tid()
        s = sample[t]
        fu, fv, bz, be = per[0, s], per[1, s], per[2, s], per[3, s]
        p_ = phases[t]
        st = stride[t]
        for j in range(2):
            for i in range(2):
                base = at[t] + wp.int64(j) * p_ + st * (wp.int64(i) * p_)
                top = pixels[base + wp.int64(1)] + fu * (pixels[base] - pixels[base + wp.int64(1)])
                bottom = pixels[base + st + wp.int64(1)] + fu * (
                    pixels[base + st] - pixels[base + st + wp.int64(1)])
                patch = bottom + fv * (top - bottom)
                p = pix0[t]
                if i == 1:
                    p = pix1[t]
                p = p + wp.int64(j)
                w = patch / (1.0 + wp.exp(wp.clamp(bz - be * scene[p], -40.0, 40.0)))
                for c in range(channels):   # one thread on the CPU: plain additions
                    acc[c, int(p)] = acc[c, int(p)] + w * per[4 + c, s]

    return wp, splat_blocks


def captured_forward(name: str):
    """The arguments of the splat's forward pass for ``name`` on the bench scene."""
    import weathergen.engine.rendering.splat as sp
    from engine_scenes import bench_scene
    from weathergen.engine import BETA_ATTACK, load_preset, render_pair, sample_particles

    pair = bench_scene()
    parts = sample_particles(pair, load_preset(name), seed=0)
    captured, original = {}, sp._Splat.forward

    def keep(ctx, u, v, z, theta, color, plan):
        captured["args"] = (u.detach(), v.detach(), z.detach(), theta.detach(), color.detach(),
                            plan)
        return original(ctx, u, v, z, theta, color, plan)

    sp._Splat.forward = staticmethod(keep)
    try:
        with torch.no_grad():
            render_pair(pair, parts, beta=BETA_ATTACK)
    finally:
        sp._Splat.forward = staticmethod(original)
    return captured["args"], original


def cpu_seconds(fn, repeats: int = 3) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.process_time()
        fn()
        times.append(time.process_time() - t0)
    return statistics.median(times)


def main(argv=None) -> int:
    import weathergen.engine.rendering.splat as sp

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=["sparks", "rain"])
    parser.add_argument("--compile", action="store_true", help="also the torch.compile route")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    wp, kernel = warp_kernel()
    compiled = torch.compile(chunk_terms, dynamic=True) if args.compile else None
    print("| preset | pixel-samples | eager ns | compiled ns (max diff) | warp ns (max diff) |")
    print("|---|---:|---:|---:|---:|")
    for name in args.presets:
        (u, v, z, theta, color, plan), forward = captured_forward(name)
        channels = 1 + color.shape[1]
        per, _ = sp._per_sample(plan, u, v, z, theta, color, weights=True)
        no_ctx = type("Ctx", (), {"save_for_backward": lambda *a: None})()
        reference = forward(no_ctx, u, v, z, theta, color, plan)
        blocks = sum(hi - lo for *_, pieces in plan.slabs for (_, _, lo, hi, _) in pieces)
        px = 4 * blocks

        def with_function(fn):
            acc = torch.zeros(channels, plan.grids.size, dtype=per.dtype)
            for chunk in plan.chunks():
                flat, terms = fn(plan.stamps.pixels, plan.scene, per, *block_arrays(*chunk),
                                 channels)
                acc.scatter_add_(1, flat.expand(channels, -1), terms)
            return acc

        def with_warp():
            acc = torch.zeros(channels, plan.grids.size, dtype=torch.float32)
            fixed = [wp.from_torch(t.float().contiguous())
                     for t in (per, plan.stamps.pixels, plan.scene)]
            for chunk in plan.chunks():
                arrays = [wp.from_torch(t.contiguous()) for t in block_arrays(*chunk)]
                wp.launch(kernel, dim=arrays[0].shape[0],
                          inputs=[*arrays, *fixed, channels, wp.from_torch(acc)], device="cpu")
            return acc

        eager = cpu_seconds(lambda: forward(no_ctx, u, v, z, theta, color, plan))
        cells = [f"{eager * 1e9 / px:.1f}"]
        for fn in (compiled and (lambda: with_function(compiled)), kernel and with_warp):
            if not fn:
                cells.append("–")
                continue
            diff = float((fn() - reference).abs().max())
            cells.append(f"{cpu_seconds(fn) * 1e9 / px:.1f} ({diff:.1e})")
        print(f"| {name} | {px:,} | " + " | ".join(cells) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
