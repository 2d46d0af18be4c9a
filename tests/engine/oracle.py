"""A naive renderer: the render core's model written loop by loop, for clarity, not speed.

For every frame pair, every frame, every particle that frame draws, every blur sample and every
grid pixel near it, it reads the stamp at that pixel's offset from the sample's exact position
(interpolated bilinearly between the stamp's values, which lie a pixel apart or, for small stamps,
1 / P pixel apart) and adds it times the visibility and θ / K; then it brings coarse grids to the
image grid and blends. Nothing is shared with the engine's code but the model's constants
(pytorch3d tests its rasterizer the same way). Two number types run through the same loops: Python floats (fast
enough for forward comparisons on small scenes) and 0-d float64 tensors that require grad (for
gradient comparisons on tiny ones).
"""

from __future__ import annotations

import math

import torch

from weathergen.engine.sampling.pair import NEAR
from weathergen.engine.rendering.stamps import COARSE_MAX_LEVEL, COARSE_MIN_SIDE, COARSE_SIDE, RIM_MARGIN
from weathergen.engine.rendering.tracks import MAX_BLUR_SAMPLES
from weathergen.engine.views import MAX_DEFOCUS


# -- number helpers: floats or 0-d tensors ---------------------------------------------------

def _exp(x):
    return torch.exp(x) if isinstance(x, torch.Tensor) else math.exp(min(x, 700.0))


def _value(x) -> float:
    return float(x.detach()) if isinstance(x, torch.Tensor) else float(x)


def _stack(rows):
    """Nested lists of numbers -> a float64 tensor (a differentiable stack where needed)."""
    if isinstance(rows, list):
        return torch.stack([_stack(r) for r in rows])
    return rows if isinstance(rows, torch.Tensor) else torch.tensor(float(rows), dtype=torch.float64)


# -- stamps ---------------------------------------------------------------------------------

def allowed_sides(limit: int = 8193) -> list:
    """Odd sides up to 15, then each the odd number at or above 1.15 times the last."""
    sides = [3, 5, 7, 9, 11, 13, 15]
    while sides[-1] < limit:
        nxt = math.ceil(sides[-1] * 1.15)
        sides.append(nxt if nxt % 2 else nxt + 1)
    return sides


SIDES = allowed_sides()


def mip_levels(alphas: torch.Tensor) -> list:
    """The templates (float64 lists of rows) and their 2 x 2 averages while even and >= 4."""
    levels = [alphas.double().tolist()]
    while len(levels[-1][0]) % 2 == 0 and len(levels[-1][0]) >= 4:
        last = levels[-1]
        r = len(last[0]) // 2
        levels.append([[[(t[2 * i][2 * j] + t[2 * i][2 * j + 1] + t[2 * i + 1][2 * j]
                          + t[2 * i + 1][2 * j + 1]) / 4 for j in range(r)] for i in range(r)]
                       for t in last])
    return levels


def geometry(footprint: float, defocus: int, resolution: int, level_count: int, coarse_side):
    """(grid level, footprint on it, blur radius, side, supersampling, mip level)."""
    radius = defocus if defocus > 1 else 0
    level = 0
    if coarse_side is not None and footprint + 2 * radius >= coarse_side:
        level = min(max(math.floor(math.log2((footprint + 2 * radius) / COARSE_MIN_SIDE)), 1),
                    COARSE_MAX_LEVEL)
        f = 2 ** level
        footprint = max(footprint / f, 1.0)
        radius = math.floor(radius / f + 0.5)
    raw = 2 * max(math.floor(footprint / 2 + 0.5), 1) + 1
    side = next(s for s in SIDES if s >= raw)
    sub = 4 if side <= 5 else (2 if side <= 9 else 1)
    mip = min(max(math.floor(math.log2(resolution / (footprint * sub))), 0), level_count - 1)
    phases = sub if radius == 0 else 1
    return level, footprint, radius, side, sub, mip, phases


#: ``brighten`` of a research stamp: brightened, not softened.
UNSOFTENED = 2


def stamp(levels, template: int, footprint: float, defocus: int, rotation: float,
          brighten: bool, resolution: int, coarse_side):
    """A stamp entry's grid level, its phases P and its values ``{(iy, ix): alpha}`` at
    ``(iy, ix) / P`` pixels from the centre (P = 1: its pixels; P > 1: small stamps sampled
    every 1 / P pixel, each value the template averaged over the pixel square centred there)."""
    level, footprint, radius, side, sub, mip, phases = geometry(footprint, defocus, resolution,
                                                                len(levels), coarse_side)
    tmpl = levels[mip][template]
    res = len(tmpl)
    half = (side - 1) // 2
    c, s = math.cos(rotation), math.sin(rotation)
    pixels = {}
    reach = half if phases == 1 else phases * (half + 1)
    for i in range(-reach, reach + 1):
        for j in range(-reach, reach + 1):
            total = 0.0
            for si in range(sub):
                for sj in range(sub):
                    gx = j / phases + (sj + 0.5) / sub - 0.5
                    gy = i / phases + (si + 0.5) / sub - 0.5
                    # the template at Rot(−rotation) (gx, gy), in half-footprints
                    xn = (c * gx + s * gy) / (footprint / 2)
                    yn = (-s * gx + c * gy) / (footprint / 2)
                    if xn * xn + yn * yn > 1 + RIM_MARGIN:
                        continue
                    px, py = (xn + 1) / 2 * res - 0.5, (yn + 1) / 2 * res - 0.5
                    x0, y0 = math.floor(px), math.floor(py)
                    for yy, wy in ((y0, 1 - (py - y0)), (y0 + 1, py - y0)):
                        for xx, wx in ((x0, 1 - (px - x0)), (x0 + 1, px - x0)):
                            if 0 <= yy < res and 0 <= xx < res:
                                total += wy * wx * tmpl[yy][xx]
            pixels[(i, j)] = total / (sub * sub)
    if radius > 0:
        disc = [(a, b) for a in range(-radius, radius + 1) for b in range(-radius, radius + 1)
                if a * a + b * b <= radius * radius]
        full = half + radius
        pixels = {(y, x): sum(pixels.get((y - a, x - b), 0.0) for a, b in disc) / len(disc)
                  for y in range(-full, full + 1) for x in range(-full, full + 1)}
    if brighten:
        pixels = {k: min((2 * max(v, 0.0)) ** (1 / 3), 1.0) for k, v in pixels.items()}
        if radius > 0 and brighten != UNSOFTENED:
            pixels = soften(pixels, radius)
    return level, phases, pixels


def soften(pixels: dict, radius: int) -> dict:
    """A brightened stamp convolved with a normalised b x b box twice, b = 2 (r // 4 + 2) + 1:
    the separable tent ``t(k) = (b − |k|) / b²`` per axis for |k| < b (the stamp grows by
    b − 1), as a 2-D sum over every tap."""
    b = 2 * (radius // 4 + 2) + 1
    tent = {k: (b - abs(k)) / (b * b) for k in range(-(b - 1), b)}
    full = max(abs(y) for y, _ in pixels) + b - 1
    return {(y, x): sum(tent[a] * tent[c] * pixels.get((y - a, x - c), 0.0)
                        for a in tent for c in tent)
            for y in range(-full, full + 1) for x in range(-full, full + 1)}


# -- what each frame draws ----------------------------------------------------------------

def _apply(cam, p):
    return [sum(cam[i][k] * p[k] for k in range(3)) + cam[i][3] for i in range(3)]


def _project(k, x):
    return ((k[0][0] * x[0] + k[0][1] * x[1]) / x[2] + k[0][2], k[1][1] * x[1] / x[2] + k[1][2])


def sample_gap(looks, coarse_side) -> float:
    """How far apart (pixels) a particle's consecutive blur samples may lie: a softened stamp
    (brightened, with a blur on its grid) is smooth over its box b, so (b − 1) / 2 of its grid's
    pixels; any other stamp one pixel of its grid."""
    _, footprint, defocus, _, brighten = looks
    level, _, radius, *_ = geometry(footprint, defocus, 1, 1, coarse_side)
    box = 2 * (radius // 4 + 2) + 1
    return 2 ** level * ((box - 1) / 2 if brighten and radius > 0 else 1.0)


def blur_count(k, x, d, reach: float, preset: int, gap: float = 1.0) -> int:
    """How many blur samples the streak ``x + s d`` (camera coordinates, s in [0, reach]) gets:
    one more than its length in ``gap`` pixels at the pixel speed of its nearer end (so
    consecutive samples lie at most ``gap`` pixels apart), at least the preset's, at most
    MAX_BLUR_SAMPLES."""
    if preset <= 1:
        return preset
    h = [sum(k[i][j] * _value(x[j]) for j in range(3)) for i in range(3)]     # K x
    g = [sum(k[i][j] * _value(d[j]) for j in range(3)) for i in range(3)]     # K d
    z_near = max(min(h[2], h[2] + reach * g[2]), NEAR)
    # d/ds of (h + s g)_u / (h + s g)_z = (g_u h_z − h_u g_z) / z², largest where z is least
    speed = math.hypot(g[0] * h[2] - h[0] * g[2], g[1] * h[2] - h[1] * g[2]) / z_near ** 2
    length = reach * speed / gap
    if not math.isfinite(length):
        return MAX_BLUR_SAMPLES
    return min(max(math.ceil(length) + 1, preset), MAX_BLUR_SAMPLES)


def farthest_around(depth, u: float, v: float, reach: float) -> float:
    """The farthest scene depth the view mask reads for a point (u, v) whose stamp reaches
    ``reach`` pixels: over the window of image pixels within ``reach`` (n x n at most), widened
    to the aligned s x s blocks that hold it (s the smallest power of two >= n)."""
    height, width = len(depth), len(depth[0])

    def span(x, size):
        lo = min(max(math.floor(x - reach + 0.5), 0), size - 1)
        hi = min(max(math.floor(x + reach + 0.5), 0), size - 1)
        return lo, hi

    (c0, c1), (r0, r1) = span(u, width), span(v, height)
    s = 1
    while s < max(c1 - c0, r1 - r0) + 1:
        s *= 2
    rows = range(r0 // s * s, min((r1 // s + 1) * s, height))
    cols = range(c0 // s * s, min((c1 // s + 1) * s, width))
    return max(depth[y][x] for y in rows for x in cols)


def _steps(reach: float, count: int) -> list:
    return [reach * i / (count - 1) if count > 1 else 0.0 for i in range(count)]


def _smoothstep(x: float) -> float:
    x = min(max(x, 0.0), 1.0)
    return x * x * (3 - 2 * x)


def draws(record, t: int, k, cams, depth, beta: float, resolution: int, number,
          coarse_side=COARSE_SIDE):
    """What frame ``t`` of a pair draws of ``record``: per drawn particle, its looks (template,
    footprint, defocus, rotation, brighten), blur samples [(u, v, z)], θ / K, colour, β and the
    middle of its streak (u, v, z).

    ``number`` turns a record value into a float or a differentiable 0-d tensor.
    """
    s = record.settings
    preset_samples = int(s.blur_samples) if int(s.blur_samples) > 1 and s.blur_length > 0 else 1
    research = s.stamp_style == "research"
    fixed = in_order(s) or research     # sample by sample, or research stamps: the preset's K
    extent = s.blur_length if preset_samples > 1 else 0.0      # the streak's length
    height, width = len(depth), len(depth[0])
    f = math.sqrt(k[0][0] * k[1][1])
    out = []
    for j in range(record.count):
        p1 = [number(record.position[j, a]) + number(record.offset1[j, a]) for a in range(3)]
        d = [number(record.motion[j, a]) + number(record.offset2[j, a]) for a in range(3)]
        p2 = [p1[a] + d[a] for a in range(3)]
        theta = number(record.transparency[j])
        colour = [number(record.color[j, a]) for a in range(3)]
        template, rotation = int(record.template[j]), float(record.rotation[j])
        if record.optics is None:
            # the paper's model: looks fixed at sampling; the streak along X2 − X1
            x1, x2 = _apply(cams[0], p1), _apply(cams[1], p2)
            xt = x1 if t == 0 else x2
            along = [x2[a] - x1[a] for a in range(3)]
            footprint = float(record.scale[j]) * resolution
            if research:        # the disc of the area of the research code's n x n window (at most f)
                footprint = min(math.floor(footprint) * 2 / math.sqrt(math.pi), footprint)
            bright = bool(s.defocus_brighten) and int(record.defocus[j]) > 1
            looks = (template, max(footprint, 1.0), int(record.defocus[j]), rotation,
                     UNSOFTENED if bright and research else bright)
            samples = preset_samples if fixed else blur_count(
                k, xt, along, s.blur_length, preset_samples, sample_gap(looks, coarse_side))
            points = [[xt[a] + q * along[a] for a in range(3)]
                      for q in _steps(s.blur_length, samples)]
            middle = [xt[a] + 0.5 * extent * along[a] for a in range(3)]
            weight, b = theta, beta
        else:
            # a weather field: this frame's looks from this frame's depth of the particle
            o = record.optics
            start = p1 if t == 0 else p2
            x = _apply(cams[t], start)
            z = _value(x[2])
            if not o.near <= z <= o.far:
                continue
            diameter = float(record.scale[j])
            footprint = f * diameter / z
            coc = 0.0 if o.aperture <= 0 else min(max(0.5 * f * o.aperture
                                                      * abs(1 / z - 1 / o.focus), 0.0),
                                                  MAX_DEFOCUS)
            radius = math.floor(coc + 0.5) if o.aperture > 0 else 0
            reach = 0.5 * footprint + radius + 2
            seen = False
            for end in (start, [start[a] + s.blur_length * d[a] for a in range(3)]):
                xe = [_value(v) for v in _apply(cams[t], end)]
                if xe[2] <= 1e-6:
                    continue
                u, v = _project(k, xe)
                if not (-0.5 - reach <= u <= width - 0.5 + reach
                        and -0.5 - reach <= v <= height - 0.5 + reach):
                    continue
                seen = seen or xe[2] <= farthest_around(depth, u, v, reach) \
                    + 3 * o.depth_softness
            fade = _smoothstep((z - o.near) / o.near) * (
                _smoothstep((o.far - z) / (o.fade * o.far)) if o.fade > 0 else float(z <= o.far))
            factor = fade * min(footprint, 1.0) ** 2
            if not seen or factor * _value(theta) == 0:
                continue
            along = [sum(cams[t][i][a] * d[a] for a in range(3)) for i in range(3)]  # R d
            looks = (template, max(footprint, 1.0), radius, rotation,
                     bool(s.defocus_brighten) and radius > 1)
            samples = preset_samples if fixed else blur_count(
                k, _apply(cams[t], start), along, s.blur_length, preset_samples,
                sample_gap(looks, coarse_side))
            points = [_apply(cams[t], [start[a] + q * d[a] for a in range(3)])
                      for q in _steps(s.blur_length, samples)]
            middle = _apply(cams[t], [start[a] + 0.5 * extent * d[a] for a in range(3)])
            weight, b = theta * factor, min(beta, 1 / o.depth_softness)
        projected = []
        for x in points:
            u, v = _project(k, x)
            projected.append((u, v, x[2]))
        out.append((looks, projected, weight / samples, colour, b, (*_project(k, middle),
                                                                     middle[2])))
    return out


# -- splatting, upsampling, blending ------------------------------------------------------

def block_depth(depth, f: int):
    """The scene depth averaged over f x f blocks, the image's edge replicated."""
    height, width = len(depth), len(depth[0])
    h, w = -(-height // f), -(-width // f)
    return [[sum(depth[min(y * f + a, height - 1)][min(x * f + b, width - 1)]
                 for a in range(f) for b in range(f)) / (f * f) for x in range(w)]
            for y in range(h)]


def upsample(grid, f: int, height: int, width: int):
    """Bilinear upsampling by f (pixel centres aligned, edges replicated), cropped."""
    h, w = len(grid), len(grid[0])

    def taps(dst, n):
        src = max((dst + 0.5) / f - 0.5, 0.0)
        i0 = math.floor(src)
        return i0, min(i0 + 1, n - 1), src - i0

    out = []
    for y in range(height):
        y0, y1, ly = taps(y, h)
        row = []
        for x in range(width):
            x0, x1, lx = taps(x, w)
            row.append((1 - ly) * ((1 - lx) * grid[y0][x0] + lx * grid[y0][x1])
                       + ly * ((1 - lx) * grid[y1][x0] + lx * grid[y1][x1]))
        out.append(row)
    return out


def frame_sums(depth, frame_draws, levels, resolution, coarse_side, detach_occlusion=False,
               depth_aware=True):
    """The sums A, C_r, C_g, C_b and the depth sum Z = Σ θ B V z of what a frame draws, on the
    image grid. Shape: -> (5, H, W) float64. ``depth_aware``: coarse grids drawn against the
    nearest and farthest depth of each coarse pixel's footprint and brought to the image grid
    pixel by pixel (:func:`across_edges`); else against the blocks' mean depth."""
    height, width = len(depth), len(depth[0])
    grids = frame_grids(depth, frame_draws, levels, resolution, coarse_side, detach_occlusion,
                        depth_aware)
    total = torch.zeros(5, height, width, dtype=torch.float64)
    for level in sorted(grids, reverse=True):
        sums = grids[level]
        if level and depth_aware:
            sums = across_edges(sums, depth, 2 ** level)
        elif level:
            sums = [upsample(s, 2 ** level, height, width) for s in sums]
        total = total + _stack(sums)
    return total


# -- coarse grids across depth edges ---------------------------------------------------------

def footprint_depth(depth, f: int, pick):
    """``pick`` (min or max) of the scene depth over each coarse pixel's footprint: the image
    pixels ``f j − f / 2 .. f j + 3 f / 2 − 1`` per axis, clamped to the image."""
    height, width = len(depth), len(depth[0])
    h, w = -(-height // f), -(-width // f)

    def span(j, size):
        return range(max(f * j - f // 2, 0), min(f * j + 3 * f // 2, size))

    return [[pick(depth[y][x] for y in span(i, height) for x in span(j, width))
             for j in range(w)] for i in range(h)]


def squash(z: float) -> float:
    return 1 - 1 / (1 + z)


def rank_in_front(keys, group: int, depth: float) -> float:
    """The share of a group's coarse blur samples (their keys ``group + squash(z)``) nearer than
    ``depth``."""
    key = float(group) + squash(depth)
    return sum(1 for k in keys if k < key) / max(len(keys), 1)


def _clamp(x, lo, hi):
    return x.clamp(lo, hi) if torch.is_tensor(x) else min(max(x, lo), hi)


def _max(a, b):
    return torch.maximum(torch.as_tensor(a, dtype=torch.float64), torch.as_tensor(
        b, dtype=torch.float64)) if torch.is_tensor(a) or torch.is_tensor(b) else max(a, b)


def _min(a, b):
    return torch.minimum(torch.as_tensor(a, dtype=torch.float64), torch.as_tensor(
        b, dtype=torch.float64)) if torch.is_tensor(a) or torch.is_tensor(b) else min(a, b)


def _sqrt(x):
    return torch.sqrt(x) if torch.is_tensor(x) else math.sqrt(x)


def across_edges(grid, depth, f: int):
    """A coarse level drawn twice (``grid``: near sums A, C_r, C_g, C_b, Z, then the far ones,
    the moments ``Σ θ B ΔV φ`` and ``Σ θ B ΔV φ²`` near and far, the footprints' depths, the
    level's sample keys and group) brought to the image grid: the near sums upsampled
    bilinearly, plus at each pixel, from each of its four coarse neighbours j whose sums differ,
    its bilinear weight times the share of the difference in front of the pixel: a ramp over
    the ranks ``mean ± √3 sd`` (sd at least a quarter rank), clipped to the ranks in front of
    the footprint's nearest and farthest depth, at the pixel's rank."""
    near, far, moments, (d_near, d_far), keys, group = grid
    height, width = len(depth), len(depth[0])
    h, w = len(near[0]), len(near[0][0])
    spread = 0.25 / max(len(keys), 1)
    out = [upsample(s, f, height, width) for s in near]

    def taps(dst, n):
        src = max((dst + 0.5) / f - 0.5, 0.0)
        i0 = math.floor(src)
        return ((i0, 1 - (src - i0)), (min(i0 + 1, n - 1), src - i0))

    for y in range(height):
        for x in range(width):
            rank = rank_in_front(keys, group, depth[y][x])
            for cy, wy in taps(y, h):
                for cx, wx in taps(x, w):
                    delta = [far[c][cy][cx] - near[c][cy][cx] for c in range(5)]
                    if all(_value(d) == 0 for d in delta[:4]):
                        continue
                    mass = delta[0]
                    m1 = (moments[2][cy][cx] - moments[0][cy][cx]) / mass if _value(mass) > 0 \
                        else 0.0
                    m2 = (moments[3][cy][cx] - moments[1][cy][cx]) / mass if _value(mass) > 0 \
                        else 0.0
                    mean = _clamp(m1, 0.0, 1.0)
                    sd = _sqrt(_clamp(m2 - mean * mean, 0.0, math.inf) + spread * spread)
                    lo = _max(mean - math.sqrt(3) * sd,
                              rank_in_front(keys, group, d_near[cy][cx]))
                    hi = _max(_min(mean + math.sqrt(3) * sd,
                                   rank_in_front(keys, group, d_far[cy][cx])), lo)
                    span = hi - lo
                    share = float(rank > _value(lo)) if _value(span) <= 0 \
                        else _clamp((rank - lo) / span, 0.0, 1.0)
                    for c in range(4):
                        out[c][y][x] = out[c][y][x] + wy * wx * share * delta[c]
    return out


def read_grids(grids, u, v):
    """A layer's A and Z at the image point (u, v): each grid level's sums interpolated
    bilinearly at ((u + 0.5) / f − 0.5, (v + 0.5) / f − 0.5), clamped to the grid (the edge
    replicated), added over the levels."""
    a_total, z_total = 0.0, 0.0
    for level, sums in grids.items():
        f = 2 ** level
        h, w = len(sums[0]), len(sums[0][0])
        x = min(max((u + 0.5) / f - 0.5, 0.0), w - 1)
        y = min(max((v + 0.5) / f - 0.5, 0.0), h - 1)
        x0, y0 = math.floor(_value(x)), math.floor(_value(y))
        x1, y1 = min(x0 + 1, w - 1), min(y0 + 1, h - 1)
        fx, fy = x - x0, y - y0

        def at(plane):
            return (1 - fy) * ((1 - fx) * plane[y0][x0] + fx * plane[y0][x1]) \
                + fy * ((1 - fx) * plane[y1][x0] + fx * plane[y1][x1])

        a_total = a_total + at(sums[0])
        z_total = z_total + _value(at(sums[4]))
    return a_total, z_total


def coarse_ranks(frame_draws, stamps, height: int, width: int):
    """The depth rank ``φ = (k + 1/2) / n`` of every blur sample drawn on a coarse grid (in
    front of the camera, its patch touching the grid) among its level's, per (draw, sample),
    and each level's sorted keys ``level + squash(z)`` (the group of the level in a one-view
    frame)."""
    drawn = []
    for i, ((_, samples, *_), (level, _, pixels)) in enumerate(zip(frame_draws, stamps)):
        if not level:
            continue
        f = 2 ** level
        h, w = -(-height // f), -(-width // f)
        q = max(abs(dx) for _, dx in pixels) + 1
        for k, (u, v, z) in enumerate(samples):
            cu = math.floor(_value((u + 0.5) / f - 0.5))
            cv = math.floor(_value((v + 0.5) / f - 0.5))
            if _value(z) > NEAR and cu + q >= 0 and cu - q + 1 <= w - 1 and cv + q >= 0 \
                    and cv - q + 1 <= h - 1:
                drawn.append((float(level) + squash(_value(z)), level, i, k))
    drawn.sort(key=lambda d: d[0])                  # stable: ties keep the draws' order
    ranks, keys = {}, {}
    for level in {d[1] for d in drawn}:
        mine = [d for d in drawn if d[1] == level]
        keys[level] = [d[0] for d in mine]
        for k, (_, _, i, j) in enumerate(mine):
            ranks[(i, j)] = (k + 0.5) / len(mine)
    return ranks, keys


def frame_grids(depth, frame_draws, levels, resolution, coarse_side, detach_occlusion=False,
                depth_aware=False):
    """The sums A, C_r, C_g, C_b, Z of what a frame draws on each grid level it draws on
    (level -> five lists of rows). ``depth_aware``: a coarse level is drawn against the nearest
    and the farthest depth of each coarse pixel's footprint, with the moment sums (level ->
    what :func:`across_edges` takes)."""
    height, width = len(depth), len(depth[0])
    grids = {}                       # level -> [A, C_r, C_g, C_b, Z] lists of rows
    stamps = [stamp(levels, *looks, resolution, coarse_side) for looks, *_ in frame_draws]
    ranks, keys = coarse_ranks(frame_draws, stamps, height, width) if depth_aware else ({}, {})
    passes = []
    for i, (draw, made) in enumerate(zip(frame_draws, stamps)):
        twice = depth_aware and made[0] > 0
        passes += [(i, draw, made, 0)] + ([(i, draw, made, 1)] if twice else [])
    moments = {}
    for i, (_, samples, theta, colour, b, _), (level, phases, pixels), copy in passes:
        reach = max(abs(dx) for _, dx in pixels) // phases + 1     # pixels from the centre
        f = 2 ** level
        key = (level, copy)
        if key not in grids:
            h, w = -(-height // f), -(-width // f)
            if level == 0:
                scene = depth
            elif depth_aware:
                scene = footprint_depth(depth, f, max if copy else min)
            else:
                scene = block_depth(depth, f)
            grids[key] = ([[[0.0] * w for _ in range(h)] for _ in range(5)], scene)
            if level and depth_aware:
                moments[key] = [[[0.0] * w for _ in range(h)] for _ in range(2)]
        sums, scene = grids[key]
        h, w = len(scene), len(scene[0])
        for n, (u, v, z) in enumerate(samples):
            if _value(z) <= NEAR:
                continue
            uc, vc = (u + 0.5) / f - 0.5, (v + 0.5) / f - 0.5       # on the level's grid
            cu, cv = math.floor(_value(uc)), math.floor(_value(vc))
            for py in range(max(cv - reach, 0), min(cv + reach + 2, h)):
                for px in range(max(cu - reach, 0), min(cu + reach + 2, w)):
                    # the stamp at this pixel's offset from the centre, interpolated
                    # bilinearly between its values 1 / P pixel apart (on a grid point: the
                    # interval that a larger u, v moves into, the core's one-sided derivative)
                    gx, gy = (px - uc) * phases, (py - vc) * phases
                    x0, y0 = math.ceil(_value(gx)) - 1, math.ceil(_value(gy)) - 1
                    corners = [pixels.get((y0 + dy, x0 + dx), 0.0)
                               for dy in (0, 1) for dx in (0, 1)]
                    if not any(corners):
                        continue
                    wx, wy = gx - x0, gy - y0
                    alpha = (1 - wy) * ((1 - wx) * corners[0] + wx * corners[1]) \
                        + wy * ((1 - wx) * corners[2] + wx * corners[3])
                    d = _value(z) if detach_occlusion else z
                    vis = 1 / (1 + _exp(b * (d - scene[py][px])))
                    a = alpha * vis * theta
                    sums[0][py][px] = sums[0][py][px] + a
                    for c in range(3):
                        sums[1 + c][py][px] = sums[1 + c][py][px] + a * colour[c]
                    sums[4][py][px] = sums[4][py][px] + a * _value(z)
                    if key in moments:
                        phi = ranks.get((i, n), 0.0)
                        moments[key][0][py][px] = moments[key][0][py][px] + a * phi
                        moments[key][1][py][px] = moments[key][1][py][px] + a * phi * phi
    out = {}
    for (level, copy), (sums, scene) in grids.items():
        if copy:
            continue
        if level and depth_aware:
            far, far_scene = grids[(level, 1)]
            out[level] = (sums, far, moments[(level, 0)] + moments[(level, 1)],
                          (scene, far_scene), keys.get(level, []), level)
        else:
            out[level] = sums
    return out


# -- the atmosphere (uniform air) ------------------------------------------------------------

def _ray_length(k, u: float, v: float) -> float:
    """``|K⁻¹ (u, v, 1)|``: distance per unit of camera depth along the ray through (u, v)."""
    y = (v - k[1][2]) / k[1][1]
    x = (u - k[0][2] - k[0][1] * y) / k[0][0]
    return math.sqrt(x * x + y * y + 1)


def air_along(atmospheres, distance: float):
    """Transmission and airlight of uniform atmospheres up to ``distance``: ``exp(−Σ τ_l)``
    with ``τ_l = β_l min(distance, sky_l)``, the airlights mixed by optical depth (one
    atmosphere: its own). The oracle integrates uniform air only."""
    taus = []
    for atm in atmospheres:
        if not atm.uniform:
            raise NotImplementedError("the oracle integrates uniform atmospheres only")
        taus.append(atm.extinction * min(max(distance, 0.0), atm.sky_distance))
    total = sum(taus)
    lights = [atm.airlight.double() for atm in atmospheres]
    if len(taus) == 1 or total <= 0:
        return math.exp(-total), lights[0]
    return math.exp(-total), sum(tau * light for tau, light in zip(taus, lights)) / total


def through_air(frame_draws, atmospheres, k, blend):
    """What a frame draws, each particle seen through the air in front of the middle of its
    streak: an additive one's θ times ``t_p``, an alpha one's colour ``γ t_p + A (1 − t_p)``."""
    if not atmospheres:
        return frame_draws
    out = []
    for looks, samples, theta, colour, b, middle in frame_draws:
        u, v, z = (_value(m) for m in middle)
        t, light = air_along(atmospheres, max(z, 0.0) * _ray_length(k, u, v))
        if blend == "alpha":
            colour = [colour[c] * t + float(light[c]) * (1 - t) for c in range(3)]
        else:
            theta = theta * t
        out.append((looks, samples, theta, colour, b, middle))
    return out


def fogged(image, depth, k, atmospheres):
    """The scene through the air, pixel by pixel, and each pixel's transmission.
    Shape: image (3, H, W) -> ((3, H, W), (1, H, W)) float64."""
    image = image.double()
    if not atmospheres:
        return image, torch.ones(1, *image.shape[1:], dtype=torch.float64)
    out = image.clone()
    trans = torch.ones(1, *image.shape[1:], dtype=torch.float64)
    for y in range(image.shape[1]):
        for x in range(image.shape[2]):
            t, light = air_along(atmospheres, depth[y][x] * _ray_length(k, x, y))
            out[:, y, x] = image[:, y, x] * t + light * (1 - t)
            trans[0, y, x] = t
    return out, trans


def in_order(settings) -> bool:
    """Whether a record's blur samples are blended one after another (``blur_blend``
    sequential, alpha, motion blur)."""
    return (settings.blur_blend == "sequential" and settings.blend == "alpha"
            and int(settings.blur_samples) > 1 and settings.blur_length > 0)


def sample_steps(frame_draws) -> list:
    """What a frame draws, sample by sample: step k holds the k-th blur sample of every
    particle that has one (θ / K each)."""
    steps = max((len(d[1]) for d in frame_draws), default=1)
    return [[(looks, [points[i]], *rest) for looks, points, *rest in frame_draws
             if i < len(points)] for i in range(steps)]


def render_frame(image, depth, frame_draws, levels, resolution, blend, coarse_side,
                 detach_occlusion=False, k=None, atmospheres=(), ordered=False):
    """One weather frame and its opacity from what it draws, through ``atmospheres`` (uniform
    air; ``k`` the intrinsics as lists). ``ordered``: each blur sample's sums blended over the
    frame the previous ones left, clamped after each. Shape: image (3, H, W) tensor."""
    frame_draws = through_air(frame_draws, atmospheres, k, blend)
    image, trans = fogged(image, depth, k, atmospheres)
    out, kept = image, 1.0
    for step in sample_steps(frame_draws) if ordered else [frame_draws]:
        total = frame_sums(depth, step, levels, resolution, coarse_side, detach_occlusion)
        alpha, colour = total[:1], total[1:4]
        out = out * (1 - alpha) + colour if blend == "alpha" else out + colour
        out = out.clamp(0, 1)
        kept = kept * (1 - alpha.clamp(0, 1))
    opacity = 1 - kept if ordered else alpha.clamp(0, 1)
    if atmospheres:
        opacity = 1 - trans * (1 - opacity)
    return out.clamp(0, 1), opacity


def oracle_render(image1, image2, depth1, depth2, intrinsics, cam1_from_ref, cam2_from_ref,
                  records, lib, *, beta: float, coarse_side=COARSE_SIDE, grad: bool = False,
                  detach_occlusion: bool = False):
    """The render core's outputs for a batch of pairs, one record per pair (shapes as
    :func:`weathergen.engine.render`). With ``grad`` the record's float tensors are read as
    differentiable 0-d tensors, so gradients reach them. Returns (image1, image2, opacity1,
    opacity2), float64. ``detach_occlusion``: the visibility sees the particle depth as a
    constant (no gradient through it)."""
    levels = mip_levels(lib.alphas)
    outs = [[], [], [], []]
    for b, record in enumerate(records):
        k = intrinsics[b].double().tolist()
        cams = [cam1_from_ref[b].double().tolist(), cam2_from_ref[b].double().tolist()]

        def number(x):
            return x.double() if grad else float(x)

        for t, (image, depth) in enumerate(((image1[b], depth1[b]), (image2[b], depth2[b]))):
            scene = depth[0].double().tolist()
            side = coarse_side if record.settings.coarse else None
            frame = draws(record, t, k, cams, scene, beta, lib.resolution, number, side)
            atmospheres = [record.atmosphere] if record.atmosphere is not None else []
            out, opacity = render_frame(image, scene, frame, levels, lib.resolution,
                                        record.settings.blend, side, detach_occlusion,
                                        k, atmospheres, in_order(record.settings))
            outs[t].append(out)
            outs[2 + t].append(opacity)
    return tuple(torch.stack(o) for o in outs)


def passed(alpha_grids, middle):
    """The share of a particle's light that passes the alpha layers in front of it: the product
    of ``1 − clamp(A_l, 0, 1)`` over the layers whose mean depth ``Z_l / A_l`` at the middle of
    its streak (u, v, z) is nearer than it."""
    u, v, z = middle
    out = 1.0
    for grids in alpha_grids.values():
        a, depth = read_grids(grids, u, v)
        if depth < _value(z) * _value(a):
            out = out * (1 - (a.clamp(0, 1) if torch.is_tensor(a) else min(max(a, 0.0), 1.0)))
    return out


def oracle_layered(image1, image2, depth1, depth2, intrinsics, cam1_from_ref, cam2_from_ref,
                   layered, *, beta: float, coarse_side=COARSE_SIDE, grad: bool = False):
    """Combined weather, pixel by pixel: every layer's sums (its own templates) and mean depth
    ``Z / A``; at each pixel the layers sorted far to near and blended one over the other with
    their own modes, clamped at the end; opacity ``1 − Π (1 − clamp(A_l))``. One
    :class:`~weathergen.engine.LayeredParticles` per pair. Returns (image1, image2, opacity1,
    opacity2), float64."""
    from weathergen.engine import load_templates
    outs = [[], [], [], []]
    for b, stack in enumerate(layered):
        k = intrinsics[b].double().tolist()
        cams = [cam1_from_ref[b].double().tolist(), cam2_from_ref[b].double().tolist()]

        def number(x):
            return x.double() if grad else float(x)

        for t, (image, depth) in enumerate(((image1[b], depth1[b]), (image2[b], depth2[b]))):
            scene = depth[0].double().tolist()
            height, width = len(scene), len(scene[0])
            modes = [record.settings.blend for record in stack.layers]
            atmospheres = [r.atmosphere for r in stack.layers if r.atmosphere is not None]
            # with alpha and additive layers both present, the additive layers' particles are
            # dimmed by the alpha layers in front of their streak's middle, and they blend last
            dimming = "additive" in modes and any(m != "additive" for m in modes)
            grids, layers = {}, [None] * len(modes)
            for i in sorted(range(len(modes)), key=lambda i: dimming and modes[i] == "additive"):
                record = stack.layers[i]
                lib = load_templates(record.settings.templates)
                frame = draws(record, t, k, cams, scene, beta, lib.resolution, number, coarse_side)
                dimmed = dimming and modes[i] == "additive"
                if dimmed:
                    under = {j: g for j, g in grids.items() if modes[j] != "additive"}
                    frame = [(looks, samples, theta * passed(under, middle), colour, b, middle)
                             for looks, samples, theta, colour, b, middle in frame]
                frame = through_air(frame, atmospheres, k, modes[i])
                grids[i] = frame_grids(scene, frame, mip_levels(lib.alphas), lib.resolution,
                                       coarse_side)
                sums = torch.zeros(5, height, width, dtype=torch.float64)
                for level in sorted(grids[i], reverse=True):
                    planes = grids[i][level]
                    if level:
                        planes = [upsample(p, 2 ** level, height, width) for p in planes]
                    sums = sums + _stack(planes)
                if dimmed:
                    sums[4] = 0.0                         # blends as the nearest
                layers[i] = (sums, modes[i] == "alpha")
            out, trans = fogged(image, scene, k, atmospheres)
            rows, clear_rows = [], []
            for y in range(height):
                row, clear_row = [], []
                for x in range(width):
                    def mean_depth(layer):
                        a = _value(layer[0][0, y, x])
                        return _value(layer[0][4, y, x]) / a if a > 0 else 0.0
                    # stable: equal depths keep the layers' order
                    order = sorted(range(len(layers)), key=lambda i: -mean_depth(layers[i]))
                    pixel = out[:, y, x]
                    clear = 1.0
                    for i in order:
                        sums, alpha_mode = layers[i]
                        a = sums[0, y, x]
                        pixel = pixel * (1 - a) + sums[1:4, y, x] if alpha_mode \
                            else pixel + sums[1:4, y, x]
                    for sums, _ in layers:
                        clear = clear * (1 - sums[0, y, x].clamp(0, 1))
                    if atmospheres:
                        clear = clear * trans[0, y, x]
                    row.append(pixel)
                    clear_row.append(1 - clear)
                rows.append(torch.stack(row, 1))
                clear_rows.append(torch.stack(clear_row))
            outs[t].append(torch.stack(rows, 1).clamp(0, 1))
            outs[2 + t].append(torch.stack(clear_rows)[None].clamp(0, 1))
    return tuple(torch.stack(o) for o in outs)
