"""Billboard templates: grey-scale alpha maps that give each particle its shape.

Two built-in libraries ship with the package, both made by :func:`generate_templates` (our own,
seeded, deterministic generators) and stored as PNGs under ``weathergen/engine/weather/templates/``:

- ``flakes``: nearly opaque round blobs with the inner structure of a dendrite (six brighter
  arms), a hexagonal plate or a soft grain (snow, rain and sparks);
- ``dust``: nearly opaque cloud blobs with a soft texture (fog and the dust rows of the size
  sweep);
- ``haze``: wisps of haze whose alpha falls over the whole radius and reaches zero with zero
  slope, ``(1 − r²)²`` times a light texture (the weather fields' fog: overlapping clouds add
  up to haze without disc outlines).

Like the paper's billboards, ``flakes`` and ``dust`` carry a mean alpha of 0.7-0.85 inside their
disc (:data:`TEMPLATE_ALPHA_RANGE`); how transparent a particle looks comes from its θ. ``haze``
has no body: its mean alpha inside the disc is about a third (:data:`HAZE_ALPHA_RANGE`).

A preset may instead name a folder of grey-scale PNGs. Every template is treated as round: content
outside its inscribed circle is dropped, so that a rotated template never needs a larger canvas.
Templates of different sizes are centred on the largest one's square canvas.
"""

from __future__ import annotations

import functools
import hashlib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import cv2
import numpy as np
import torch

from ...errors import ConfigError, FormatError

#: The template libraries that ship with weathergen (a preset may also name a folder of PNGs).
BUILTIN_TEMPLATE_KINDS = ("flakes", "dust", "haze")

FLAKE_RESOLUTION = 80
DUST_RESOLUTION = 128
FLAKE_COUNT = 8
DUST_COUNT = 6
HAZE_RESOLUTION = 128
HAZE_COUNT = 6
# Mean alpha inside each built-in template's disc: the paper's flakes and smoke blobs are
# nearly opaque (about 0.7-0.85 inside the disc); the depth hat and θ make them transparent.
TEMPLATE_ALPHA_RANGE = (0.7, 0.85)
#: Mean alpha inside a ``haze`` template's disc: ``(1 − r²)²`` averages 1/3 over the disc.
HAZE_ALPHA_RANGE = (0.25, 0.4)
#: Largest change of a ``haze`` template's alpha per unit of radius (its template pixels times
#: the footprint's half-width in template pixels): ``(1 − r²)²`` alone has 1.54.
HAZE_MAX_SLOPE = 2.0


@dataclass(frozen=True)
class TemplateLibrary:
    """The templates a particle's ``template`` index refers to.

    Shape:
        alphas: (T, R, R) float32 in [0, 1], T templates of R x R pixels (R >= 1).
    ``name`` is the built-in kind or the folder; ``digest`` fingerprints the pixel data, so a
    stored particle record can tell whether it is re-rendered with the templates it was made with.
    """

    name: str
    alphas: torch.Tensor
    digest: str

    @property
    def count(self) -> int:
        return int(self.alphas.shape[0])

    @property
    def resolution(self) -> int:
        return int(self.alphas.shape[-1])


def _disc_mask(res: int) -> np.ndarray:
    c = (res - 1) / 2
    yy, xx = np.mgrid[0:res, 0:res]
    return ((xx - c) ** 2 + (yy - c) ** 2) <= (res / 2) ** 2


def _finish(stack: list[np.ndarray], name: str) -> TemplateLibrary:
    res = max(max(a.shape) for a in stack)
    canvas = np.zeros((len(stack), res, res), np.float32)
    for i, a in enumerate(stack):
        h, w = a.shape
        top, left = (res - h) // 2, (res - w) // 2
        canvas[i, top:top + h, left:left + w] = a
    canvas *= _disc_mask(res)
    digest = hashlib.sha256(canvas.tobytes()).hexdigest()[:16]
    return TemplateLibrary(name=name, alphas=torch.from_numpy(canvas), digest=digest)


def _read_png(path: Path) -> np.ndarray:
    if path.suffix.lower() != ".png":
        raise FormatError(path, "not a PNG image; a template folder may hold only grey-scale PNGs")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise FormatError(path, "cannot be read as an image")
    scale = 65535.0 if img.dtype == np.uint16 else 255.0
    img = img.astype(np.float32) / scale
    if img.ndim == 3:
        if img.shape[2] == 4:  # coloured template with alpha: its alpha channel is the shape
            img = img[..., 3]
        else:
            img = img[..., :3].mean(axis=2)
    if min(img.shape) < 1:
        raise FormatError(path, "empty image")
    return img


@functools.lru_cache(maxsize=8)
def _load_cached(spec: str) -> TemplateLibrary:
    if spec in BUILTIN_TEMPLATE_KINDS:
        folder = resources.files("weathergen.engine.weather") / "templates" / spec
        files = sorted((f for f in folder.iterdir() if f.name.endswith(".png")), key=lambda f: f.name)
        if not files:  # a broken installation, not a user error
            raise RuntimeError(f"built-in template library '{spec}' is missing from the package")
        stack = []
        for f in files:
            with resources.as_file(f) as p:
                stack.append(_read_png(Path(p)))
        return _finish(stack, spec)
    folder = Path(spec).expanduser()
    if not folder.is_dir():
        raise ConfigError(f"{folder}: template folder does not exist (or use one of "
                          f"{', '.join(BUILTIN_TEMPLATE_KINDS)})")
    files = sorted(f for f in folder.iterdir() if f.is_file() and not f.name.startswith("."))
    if not files:
        raise ConfigError(f"{folder}: template folder holds no PNG images")
    if len(files) > 65535:
        raise ConfigError(f"{folder}: too many templates ({len(files)}, at most 65535)")
    return _finish([_read_png(f) for f in files], str(folder))


def load_templates(spec: str) -> TemplateLibrary:
    """A built-in library (``"flakes"``, ``"dust"``) or a folder of grey-scale PNGs.

    Raises ConfigError for a missing or empty folder and FormatError naming the first file that
    is not a readable PNG.
    """
    return _load_cached(str(spec))


# ---------------------------------------------------------------------------------------------
# Generators for the built-in libraries.

def _segment_distance(xx, yy, x0, y0, x1, y1):
    """Distance of every grid point to the segment (x0, y0)-(x1, y1)."""
    dx, dy = x1 - x0, y1 - y0
    t = np.clip(((xx - x0) * dx + (yy - y0) * dy) / max(dx * dx + dy * dy, 1e-12), 0, 1)
    return np.hypot(xx - (x0 + t * dx), yy - (y0 + t * dy))


def _blob(r, radius, soft=0.25):
    """A filled disc of ``radius`` whose edge falls smoothly to 0 over the outer ``soft``
    fraction. Shape: any -> same, values in [0, 1]."""
    t = np.clip((radius - r) / (soft * radius), 0, 1)
    return t * t * (3 - 2 * t)                    # smoothstep


def _flake(rng: np.random.Generator, res: int, style: str) -> np.ndarray:
    """One flake: a filled, nearly opaque round blob (like the soft flakes of the paper's
    figures) whose inner structure varies by ``style``. Mean alpha inside the template's
    disc lies in [0.7, 0.85] (see TEMPLATE_ALPHA_RANGE)."""
    c = (res - 1) / 2
    yy, xx = np.mgrid[0:res, 0:res].astype(np.float64)
    xx, yy = (xx - c) / c, (yy - c) / c          # unit coordinates, the disc has radius 1
    r = np.hypot(xx, yy)
    ang = np.arctan2(yy, xx)
    if style == "grain":                          # a soft grain, brightest in its core
        body = _blob(r, 1.0, soft=0.2)
        alpha = body * (0.9 + 0.1 * np.exp(-(r / 0.5) ** 2))
    elif style == "plate":                        # a hexagonal plate with a bright rim
        phase = rng.uniform(0, np.pi / 3)
        hexr = np.cos(np.pi / 6) / np.cos(((ang - phase) % (np.pi / 3)) - np.pi / 6)
        edge = r / (rng.uniform(1.08, 1.15) * hexr)
        body = _blob(edge, 1.0, soft=0.15) * _blob(r, 1.0, soft=0.12)
        alpha = body * (0.88 + 0.12 * np.exp(-(edge - 0.75) ** 2 / 0.02))
    else:                                         # a dendrite: six brighter arms in a soft disc
        arms = 6
        phase = rng.uniform(0, 2 * np.pi / arms)
        width = rng.uniform(0.08, 0.12)
        dist = np.full_like(r, np.inf)
        for k in range(arms):
            a = phase + 2 * np.pi * k / arms
            dist = np.minimum(dist, _segment_distance(xx, yy, 0, 0, np.cos(a), np.sin(a)))
        body = _blob(r, 1.0, soft=0.18)
        alpha = body * (0.88 + 0.12 * np.exp(-(dist / width) ** 2))
    return (alpha / alpha.max()).astype(np.float32)


def _smooth_noise(rng: np.random.Generator, res: int, cells: int) -> np.ndarray:
    """Band-limited noise: a coarse random grid, upsampled bicubically-ish by separable cosines."""
    coarse = rng.uniform(0, 1, size=(cells + 3, cells + 3))
    pos = np.linspace(1, cells + 1, res)
    i = np.floor(pos).astype(int)
    f = pos - i
    w = (1 - np.cos(np.pi * f)) / 2               # cosine interpolation weights
    rows = coarse[i] * (1 - w)[:, None] + coarse[i + 1] * w[:, None]
    return rows[:, i] * (1 - w)[None, :] + rows[:, i + 1] * w[None, :]


def _dust(rng: np.random.Generator, res: int) -> np.ndarray:
    """A cloud: overlapping soft puffs with a band-limited texture, nearly opaque in its body
    (mean alpha inside the disc in [0.7, 0.85], like the paper's smoke blobs)."""
    c = (res - 1) / 2
    yy, xx = np.mgrid[0:res, 0:res].astype(np.float64)
    xx, yy = (xx - c) / c, (yy - c) / c
    r = np.hypot(xx, yy)
    puffs = np.zeros_like(r)
    for _ in range(rng.integers(4, 8)):           # overlapping soft puffs make a cloud
        cx, cy = rng.uniform(-0.25, 0.25, size=2)
        s = rng.uniform(0.3, 0.45)
        puffs += rng.uniform(0.5, 1.0) * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * s * s))
    puffs = puffs / puffs.max()
    texture = 0.6 * _smooth_noise(rng, res, 4) + 0.4 * _smooth_noise(rng, res, 9)
    body = _blob(r, 1.0, soft=0.15) * np.clip(0.85 + 0.3 * puffs, 0, 1)
    alpha = body * (0.88 + 0.12 * texture)
    return (alpha / alpha.max()).astype(np.float32)


def _haze(rng: np.random.Generator, res: int) -> np.ndarray:
    """A wisp of haze: alpha ``(1 − r²)² (0.85 + 0.15 texture)``, falling over the whole radius
    to zero with zero slope at the rim (no outline however large it is drawn), its texture
    band-limited to a few cells across (so it adds little slope: at most
    :data:`HAZE_MAX_SLOPE` per unit of radius in all)."""
    c = (res - 1) / 2
    yy, xx = np.mgrid[0:res, 0:res].astype(np.float64)
    r2 = ((xx - c) ** 2 + (yy - c) ** 2) / (res / 2) ** 2
    texture = 0.7 * _smooth_noise(rng, res, 2) + 0.3 * _smooth_noise(rng, res, 4)
    texture = (texture - texture.min()) / max(np.ptp(texture), 1e-12)
    alpha = np.clip(1 - r2, 0, 1) ** 2 * (0.85 + 0.15 * texture)
    return (alpha / alpha.max()).astype(np.float32)


def generate_templates(kind: str, seed: int = 0) -> list[np.ndarray]:
    """The built-in templates of ``kind`` as (R, R) float32 arrays in [0, 1], deterministic."""
    rng = np.random.default_rng(seed)
    if kind == "flakes":
        styles = ["dendrite", "dendrite", "dendrite", "plate", "plate", "grain", "grain", "dendrite"]
        return [_flake(rng, FLAKE_RESOLUTION, s) for s in styles[:FLAKE_COUNT]]
    if kind == "dust":
        return [_dust(rng, DUST_RESOLUTION) for _ in range(DUST_COUNT)]
    if kind == "haze":
        return [_haze(rng, HAZE_RESOLUTION) for _ in range(HAZE_COUNT)]
    raise ConfigError(f"unknown template kind '{kind}' (known: {', '.join(BUILTIN_TEMPLATE_KINDS)})")


def write_builtin_templates(root: str | Path, seed: int = 0) -> list[Path]:
    """Regenerate the shipped PNGs under ``root/<kind>/NN.png`` (run from a source checkout:
    ``python -c "from weathergen.engine.weather.templates import write_builtin_templates as w;
    w('weathergen/engine/weather/templates')"``)."""
    written = []
    for kind in BUILTIN_TEMPLATE_KINDS:
        folder = Path(root) / kind
        folder.mkdir(parents=True, exist_ok=True)
        for i, a in enumerate(generate_templates(kind, seed)):
            path = folder / f"{i:02d}.png"
            cv2.imwrite(str(path), np.round(a * 255).astype(np.uint8))
            written.append(path)
    return written
