"""Stage 2 of the render core: looks -> stamps (no gradient).

Each stamp entry's template (:class:`~weathergen.engine.rendering.tracks.Looks`) is rotated and scaled to
its own footprint on a pixel-centred grid, sampled from a mip level no finer than twice the
footprint (no aliasing for far, tiny particles), zero outside the footprint's disc. Small stamps
without a defocus blur are *phase stamps* (:data:`PHASE_SIDE`): sampled every 1 / P pixel
(P = 4 up to 5 pixels wide, 2 up to 9), each value the template averaged over the pixel square
centred there, so that the splat can place them at a particle's exact sub-pixel position; the
others are sampled once per pixel (small blurred ones box-filtered: 4 x 4 or 2 x 2 samples); then
disc-blurred by the defocus radius (a normalised disc, the stamp growing by 2 r) and brightened
where asked (:func:`defocus_brighten`); a brightened stamp is then softened by a normalised box
of :func:`soft_box` applied twice (a tent per axis: it keeps the rule's light and turns the rim
the brightening lifts into a ramp; the stamp grows by ``b − 1`` on each side). Stamps at least
:data:`COARSE_SIDE` pixels wide (fog, large dust) are drawn for a grid ``2**L`` times coarser than the image (see
:func:`stamp_geometry`). A stamp's looks are this package's alone: how a template is sampled, the
disc that cuts it, the defocus kernel. A record's stored stamps (:func:`stored`: the paper's
published weather) are drawn at their own pixels instead.

Layout (:class:`StampSet`): every stamp with a one-pixel zero border, row-major, one after the
other in one flat tensor; ragged, so a call costs a bounded number of tensor operations:

- samples: every stamp pixel's ``sub x sub`` sample positions are computed for all entries at
  once (with a GPU's chunks; group by supersampling factor with the CPU's) and read with one
  ``grid_sample`` from an atlas holding every mip level of every template (one-pixel zero
  borders between them, so a read never bleeds into a neighbour); entries of several template
  libraries (:func:`build_many`) are built together, only the reads going library by library;
- disc blur: the disc is a stack of rows of half-width ``w(dy)``; a blurred pixel sums, over the
  disc's rows, box sums of the stamp's rows, each the difference of two prefix sums. Prefix sums
  are taken per stamp row (never across stamps, so a stamp does not depend on the others), in
  float64 (where a row is all zeros the difference is exactly zero: blurred stamps stay exactly
  zero outside their support);
- phase stamps: samples at every 1 / P pixel (all sides in one ragged pass with a GPU's
  chunks, one dense batch per side with the CPU's), averaged over P x P windows (separable
  pairwise sums) and copied to the stamps' places;
- softening: stamps grouped by similar sides (work proportional to their pixels, not to the
  count times the largest), disc-blurred straight onto their group's canvases, four box passes
  per group, each along one axis of every stamp at
  once (differences of per-row or per-column prefix sums in float64, as the disc blur).

Elementwise operations are those whose result does not depend on an element's position in its
tensor (``exp``/``log`` rather than ``pow`` and ``sigmoid``, whose vectorised and scalar CPU
kernels round differently), so a stamp is the same whatever other stamps the call holds.
"""

from .building import StampSet, build, build_many, stored
from .filters import defocus_brighten
from .atlas import atlas, mip_pyramid
from .tables import (COARSE_MAX_LEVEL, COARSE_MIN_SIDE, COARSE_SIDE, PHASE_FACTORS, PHASE_SIDE,
                     RIM_MARGIN, SIDES, STAMP_CHUNK_ELEMENTS, disc_counts, floor_log2, soft_box,
                     stamp_geometry)

__all__ = ["COARSE_MAX_LEVEL", "COARSE_MIN_SIDE", "COARSE_SIDE", "PHASE_FACTORS", "PHASE_SIDE",
           "RIM_MARGIN", "SIDES", "STAMP_CHUNK_ELEMENTS", "StampSet", "atlas", "build", "build_many",
           "defocus_brighten", "disc_counts", "floor_log2", "mip_pyramid", "soft_box",
           "stamp_geometry", "stored"]
