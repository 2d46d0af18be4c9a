"""Stage 3 of the render core: blur samples and stamps -> per-pixel sums, differentiably.

Every blur sample (:class:`~weathergen.engine.rendering.tracks.Instances`) leaves its entry's stamp
(:class:`~weathergen.engine.rendering.stamps.StampSet`) placed at its sub-pixel position: each pixel of an
``(s + 1) x (s + 1)`` patch ``B`` reads the stamp at its offset from the sample, interpolated
bilinearly between the stamp's values (a pixel apart; 1 / P pixel for phase stamps, whose P
phases per axis are read at stride P: differentiable in the position), times the
visibility ``V = 1 / (1 + exp(β (d − D)))`` of its depth ``d`` against the scene depth ``D``
under each patch pixel, times its ``θ / K``; the products are added into per-pixel sums
``A = Σ θ B V`` and ``C_c = Σ γ_c θ B V`` (:class:`Sums`), one plane per view. Entries drawn on
a coarse grid (large billboards) are splatted into that grid's planes, at ``(u + 0.5) / f − 0.5``,
twice: against the nearest and against the farthest scene depth of each coarse pixel's footprint,
with two more channels, the sums of ``θ B V φ`` and ``θ B V φ²`` (``φ`` the blur sample's depth
rank; :mod:`~weathergen.engine.rendering.coarse`), from which :mod:`~weathergen.engine.rendering.planes` brings
them to the image grid, pixel by pixel across depth edges (``depth_aware=False``: once, against
the scene depth averaged over ``f x f`` blocks, upsampled bilinearly).

Layout: a patch has an even side (stamp sides are odd), so it is cut into 2 x 2 blocks: a
sample's blocks are rows of blocks, and the rows of every sample of the call are one ragged run
(what a block needs is computed once per row of blocks, a slab of chunks at a time, from a few
numbers per sample: a row's are its sample's plus multiples of its place in the sample). Per block the stamp's
4 x 4 neighbourhood (rows and columns 0, 1, P, P + 1 from the block's first grid point) is read
in one gather (3 x 3 where every stamp of the chunk has P = 1, which the plan knows on the
host) and the four pixels are computed side by side (element arrays are
(2, 2, blocks): a block's numbers broadcast along the last, contiguous axis). A grid plane has a
margin left and right as wide as the call's widest patch and one extra row below, where patch
pixels outside the image land (their scene depth is −∞: V = 0, they add nothing; rows outside
the image are sent to the extra row), so no pixel needs a bounds check.

Memory: :class:`_Splat` keeps, for the backward pass, a few numbers per blur sample and recomputes
each chunk of patch pixels (at most ``chunk_elements``), so memory is bounded by the chunk size
with or without gradients, whatever the particles' footprints.

Order: on the CPU the samples of one plane are added in one order whatever else the call holds
and whatever the chunk size (a plane is cut into pieces of :data:`PLANE_SPLIT` blocks counting
from its start, see :func:`~weathergen.engine.rendering.ragged.runs`), and every elementwise
operation gives the same bits at any position of its tensor, so a pair's frames are the same
bytes alone or in a batch. On CUDA the additions are atomic, and their order (the last bits) may
change between runs.
"""

from __future__ import annotations

from typing import Optional

import torch

from ..common import NEAR
from .coarse import CoarseDepths, DepthOrder, moment_channels
from .planes import Grids, Sums, grids_for, scene_depths
from .ragged import chunk_spans
from .stamps import COARSE_MAX_LEVEL, StampSet
from .tracks import Instances

#: Patch pixels handled per chunk on the CPU (each costs about a hundred bytes of temporaries).
SPLAT_CHUNK_ELEMENTS = 1 << 16
#: On a GPU, chunks take at most this share of the free memory (and at most 2**25 elements).
GPU_MEMORY_SHARE = 0.25
BYTES_PER_ELEMENT = 256
#: On the CPU, planes of more blocks are splatted in pieces of this many blocks.
PLANE_SPLIT = SPLAT_CHUNK_ELEMENTS // 4
#: Side of the image tiles samples are sorted by within a plane (pixels).
TILE = 32
#: The visibility's exponent β (d − D) is clamped to ± this (see :class:`_Blocks`).
VISIBILITY_CLAMP = 40.0


def chunk_elements_for(device: torch.device) -> int:
    """The default chunk size on ``device``: :data:`SPLAT_CHUNK_ELEMENTS` on the CPU (small
    chunks stay in the caches); on a CUDA device as many elements as :data:`GPU_MEMORY_SHARE`
    of its free memory holds, between 2**21 and 2**25 (fewer chunks, fewer kernel launches)."""
    if device.type != "cuda":
        return SPLAT_CHUNK_ELEMENTS
    free, _ = torch.cuda.mem_get_info(device)
    return int(min(1 << 25, max(1 << 21, GPU_MEMORY_SHARE * free // BYTES_PER_ELEMENT)))


def splat(inst: Instances, stamps: StampSet, depth: torch.Tensor, *,
          chunk_elements: Optional[int] = None, detach_occlusion: bool = False,
          passive: int = 0, depth_aware: bool = True) -> Sums:
    """The per-pixel sums of every blur sample's stamp (see the module doc).

    Shape: depth (V, 1, H, W) the scene depth of the V views; returns :class:`Sums`.
    Differentiable in ``inst.u``, ``inst.v``, ``inst.theta``, ``inst.color`` and, unless
    ``detach_occlusion``, ``inst.z`` (through the visibility ``V``).
    ``passive``: how many of the last colour channels are sums no gradient comes back to (the
    depth of a layered render, which only orders the layers): the backward pass skips them.
    ``depth_aware``: coarse grids drawn against the nearest and farthest depth of each coarse
    pixel's footprint, with the moment sums (see :mod:`~weathergen.engine.rendering.coarse`); else
    against the block's mean depth.
    """
    views, _, height, width = depth.shape
    dtype = inst.u.dtype
    grids = grids_for(stamps, views, height, width, copies=2 if depth_aware else 1)
    if chunk_elements is None:
        chunk_elements = chunk_elements_for(depth.device)
    scene, footprints = scene_depths(depth, grids, dtype)
    plan = _Plan(inst, stamps, scene, grids, chunk_elements)
    plan.passive = passive
    z = inst.z.detach() if detach_occlusion else inst.z
    colour, coarse = inst.color, None
    if plan.order is not None:
        colour = moment_channels(colour, plan.rank, passive)
        coarse = CoarseDepths(depth=depth.detach()[:, 0].to(dtype), footprints=footprints,
                              order=plan.order, moments=1 + inst.color.shape[1] - passive)
    values = _Splat.apply(inst.u, inst.v, z, inst.theta, colour, plan)
    return Sums(values=values, grids=grids, reached=plan.reached, coarse=coarse)


class _Plan:
    """What a splat call draws, fixed before its autograd function runs.

    Samples kept (in front of the camera, patch touching the image), sorted by plane and image
    tile: ``kept`` (K,) int64 indices into the instances, ``entry`` (K,) their entries,
    ``phases`` (K,) P, ``fraction`` (2, K) the sub-pixel shifts of :func:`_per_sample`. A
    sample's patch is q x q blocks (q = (side + 1) / 2, ``q`` (K,)): q rows of q blocks; the
    rows of the kept samples follow each other. What a row's numbers are computed from (see
    :meth:`_slab`): ``coef`` (K, 5) int64 per sample, ``rows_of_entry`` (E, 6) int64 per entry.
    On the host, ``slabs``: runs of chunks whose rows' numbers are computed together (on the
    CPU, about :data:`SLAB_ROWS` rows: the arrays stay small, not one per row of the call),
    ``(a, b, s, t, r0, r1, pieces)``: rows a .. b − 1, of samples s .. t − 1, whose rows are r0
    .. r1 − 1, and its chunks ``(a, b, lo, hi, whole)``: rows a .. b − 1, blocks lo .. hi − 1,
    and whether every block's stamp is sampled at whole pixels (P = 1: see :class:`_Blocks`).
    Both passes use the same chunks.
    """

    def __init__(self, inst: Instances, stamps: StampSet, scene: torch.Tensor, grids: Grids,
                 chunk_elements: int):
        device = scene.device
        self.stamps, self.scene, self.grids = stamps, scene, grids
        self.dtype = inst.u.dtype
        self.beta = inst.beta
        self.blocks_per_chunk = max(1, chunk_elements // 4)
        self.cpu = device.type == "cpu"
        self.reached = torch.zeros(grids.views, dtype=torch.bool, device=device)
        self.count, self.passive = 0, 0
        self.order, self.rank = None, None
        if inst.count == 0 or stamps.count == 0:
            return
        self.coarse = grids.levels[0][0] > 0       # (coarsest first)
        with torch.no_grad():
            # per entry: its stamp's blocks per side q (its side is 2 q − 1), P, its level's grid
            side, phases = stamps.side, stamps.phases
            q = torch.div(side, 2, rounding_mode="floor").add_(1)
            grid = torch.tensor(_level_rows(grids), device=device).index_select(0, stamps.coarse)
            kept, view, uv, uv0, key = self._sorted_samples(inst, q, grid)
            if self.count == 0:
                return
            # per entry, what its rows need: q, 2 P (fine − q) (see _place), the bordered
            # stamp's row length fine, P, its level's h and row length in the sums
            fine = torch.addcmul(phases, phases, side).add_(1)
            two_p = phases + phases
            self.rows_of_entry = torch.cat((torch.stack((q, two_p * (fine - q), fine, phases),
                                                        1), grid[:, 3::2]), 1)
            # per entry, what its samples need: q, P, fine, its first stamp pixel, its level's
            # f, where its planes' pixel (0, 0) sits and a plane's length in the sums
            per_entry = torch.cat((torch.stack((q, phases, fine, stamps.first), 1),
                                   grid[:, 2::2]), 1)
            row_start, rows_end, blocks_end = self._place(inst, per_entry, kept, view, uv, uv0)
            if self.cpu:      # the module's constant, read at call time (benchmarks replace it)
                pieces = chunk_spans(self.q, self.blocks_per_chunk, key.bitwise_right_shift_(29),
                                     PLANE_SPLIT, repeats=self.q, ends=(rows_end, blocks_end))
            else:
                pieces = chunk_spans(self.q, self.blocks_per_chunk, repeats=self.q,
                                     ends=(rows_end, blocks_end))
            self._slabs(pieces, row_start, rows_end, (self.phases > 1).long())

    def _sorted_samples(self, inst: Instances, q: torch.Tensor, grid: torch.Tensor) -> tuple:
        """The blur samples to draw, sorted: those whose patch touches the image (a coarse one
        twice, see :meth:`_twice`), by plane, then by tile of the image (samples of a chunk hit
        nearby pixels: fewer cache misses in the scatter), phase stamps after the others (most
        chunks then hold one kind, see :class:`_Blocks`); the key depends on the sample alone.
        Sets ``count``. ``q`` (E,) blocks per side, ``grid`` (E, 7) the entry's level's numbers
        (see :func:`_level_rows`). Returns ``(kept, view, uv, uv0, key)``: the samples'
        instances and planes' views (K,) int64, their positions on their grids (2, K) and those
        rounded down (2, K) int64, their sort keys (K,) int64."""
        grids, stamps = self.grids, self.stamps
        kind = torch.add(stamps.phases > 1, stamps.coarse, alpha=2 * grids.views * grids.copies)
        # whether a patch touches the image: its first column and row, uv0 − q + 1, not after
        # w − 1 and h − 1; its last, uv0 + q, from 0 on
        per = torch.cat((torch.stack((q, kind), 1), grid[:, :3]), 1).index_select(0, inst.entry)
        uv = torch.stack((inst.u, inst.v))                                 # (2, I)
        if self.coarse:
            uv = _on_grid(uv, per[:, 4])
        uv0 = torch.floor(uv).long()
        reach = per[:, 0]
        keep = ((uv0 + reach >= 0) & (uv0 - reach < per[:, 2:4].t())).all(0) & (inst.z > NEAR)
        kept = torch.nonzero(keep).squeeze(1)
        # (view: the sample's plane; a coarse sample is drawn again into plane V + view)
        view = inst.view.index_select(0, kept)
        if grids.copies > 1 and self.coarse:
            kept, view = self._twice(inst, stamps.coarse, kept, view, grids.views)
        tile = torch.div(uv0.index_select(1, kept), TILE, rounding_mode="floor") \
            .clamp_(-1, 1 << 12).add_(1)
        tile_u, tile_v = tile.unbind(0)
        kind = torch.add(per[:, 1].index_select(0, kept), view, alpha=2)
        key = torch.add(torch.add(tile_u, tile_v, alpha=1 << 14), kind, alpha=1 << 28)
        key, order = torch.sort(key, stable=True)
        self.count = int(order.numel())
        kept, view = kept.index_select(0, order), view.index_select(0, order)
        return kept, view, uv.index_select(1, kept), uv0.index_select(1, kept), key

    def _place(self, inst: Instances, per_entry: torch.Tensor, kept: torch.Tensor,
               view: torch.Tensor, uv: torch.Tensor, uv0: torch.Tensor) -> tuple:
        """The kept samples' numbers (see :meth:`_sorted_samples`): sets ``entry``, ``kept``,
        ``q``, ``phases``, ``fraction``, ``factor`` (on coarse grids), ``reached`` and ``coef``.
        ``per_entry`` (E, 7): q, P, fine, first, f, origin, plane length. Returns where each
        sample's rows start and end and where its blocks end among the call's. Shape: (K,)
        int64 each."""
        self.entry = inst.entry.index_select(0, kept)
        q, phases, fine, first, f, origin, plane_len = \
            per_entry.index_select(0, self.entry).unbind(1)
        col0, row0 = (uv0 - q + 1).unbind(0)       # the patch's first column and row
        # the phase stamp's grid point at the patch's top-left pixel (see _Blocks): the
        # phase φ = floor(P f) of the sub-pixel shift f, per axis
        shift = (uv - uv0) * phases
        phase = torch.floor(shift)
        late_u, late_v = ((phases - 1) - phase.long()).unbind(0)            # P − 1 − φ
        # (what _per_sample's fu, fv are: the shift's fraction of a grid step, P f − φ)
        self.fraction = shift.sub_(phase)
        first = torch.addcmul(first, late_v, fine).add_(late_u)
        self.reached.index_fill_(0, torch.remainder(view, self.grids.views), True)
        self.kept, self.q, self.phases = kept, q, phases
        if self.coarse:
            self.factor = f.to(self.dtype)
        # a sample's row j is row row_start + j of the call, its block c block b =
        # block_start + j q + c; that block's top-left stamp pixel is first + 2 P fine j
        # + 2 P c = first − 2 P block_start + 2 P (fine − q) j + 2 P b
        blocks = q * q
        rows_end, blocks_end = torch.cumsum(q, 0), torch.cumsum(blocks, 0)
        row_start, block_start = rows_end - q, blocks_end - blocks
        self.coef = torch.stack((row_start, torch.addcmul(first, phases, block_start, value=-2),
                                 block_start, row0,
                                 torch.addcmul(origin + col0, view, plane_len)), 1)
        return row_start, rows_end, blocks_end

    def _twice(self, inst: Instances, level: torch.Tensor, kept: torch.Tensor,
               view: torch.Tensor, views: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The kept samples with those on coarse grids once more, into planes ``V + view``
        (against the footprints' farthest depth); sets ``order`` and ``rank`` (the depth order
        of the coarse samples per level and view, :class:`~weathergen.engine.rendering.coarse.DepthOrder`)."""
        at = level.index_select(0, inst.entry.index_select(0, kept))
        on = torch.nonzero(at > 0).squeeze(1)
        if on.numel() == 0:
            return kept, view
        drawn, again = kept.index_select(0, on), view.index_select(0, on)
        group = torch.add(again, at.index_select(0, on), alpha=views)
        self.order, rank = DepthOrder.of(inst.z.index_select(0, drawn), group,
                                         (COARSE_MAX_LEVEL + 1) * views)
        self.rank = torch.zeros(inst.count, dtype=torch.float64, device=kept.device) \
            .index_copy_(0, drawn, rank)
        return torch.cat((kept, drawn)), torch.cat((view, again + views))

    def _slabs(self, pieces: list, row_start: torch.Tensor, rows_end: torch.Tensor,
               phase: torch.Tensor):
        """``slabs`` from the chunks ``(a, b, lo, hi)`` (one host synchronisation): the samples
        of each chunk's first and last row, and whether phase stamps lie between."""
        ends = [x for a, b, _, _ in pieces for x in (a, b - 1)]
        sample = torch.searchsorted(rows_end, torch.tensor(ends, device=rows_end.device),
                                    right=True)
        # the phase samples up to each, its own, where its rows start and end
        seen, own, start, end = torch.stack((torch.cumsum(phase, 0), phase, row_start, rows_end)) \
            .index_select(1, sample).tolist()
        sample = sample.tolist()
        first, last = sample[0::2], sample[1::2]
        self.slabs = []
        limit = SLAB_ROWS if self.cpu else 1 << 62
        for i, (a, b, lo, hi) in enumerate(pieces):
            piece = (a, b, lo, hi, seen[2 * i + 1] == seen[2 * i] - own[2 * i])
            if self.slabs and b - self.slabs[-1][0] <= limit:
                a0, _, s, _, r0, _, held = self.slabs[-1]
                self.slabs[-1] = (a0, b, s, last[i] + 1, r0, end[2 * i + 1], held + [piece])
            else:
                self.slabs.append((a, b, first[i], last[i] + 1, start[2 * i], end[2 * i + 1],
                                   [piece]))

    def _slab(self, a: int, b: int, s: int, t: int, r0: int, r1: int) -> tuple:
        """The numbers of rows a .. b − 1 (of samples s .. t − 1, whose rows are r0 .. r1 − 1):
        q (blocks per row) and, for :class:`_Blocks`, each row's sample, the stamp pixel at the
        top left of its first block less 2 P b0 and where its two pixel rows start in the sums
        less 2 b0, for its first block b0 (a row outside the image: at the extra row), its
        stamp's stride (bordered row length) and P. Shape: (b − a,) each."""
        every = s == 0 and t == self.count
        sample = torch.repeat_interleave(self.q if every else self.q[s:t], output_size=r1 - r0)
        if a > r0 or b < r1:
            sample = sample[a - r0:b - r0]
        row_start, at, block_start, row0, plane = \
            (self.coef if every else self.coef[s:t]).index_select(0, sample).unbind(1)
        entry = (self.entry if every else self.entry[s:t]).index_select(0, sample)
        q, step, fine, phases, h, row_len = self.rows_of_entry.index_select(0, entry).unbind(1)
        j = torch.arange(a, b, device=self.q.device).sub_(row_start)
        # its pixel rows y = row0 + 2 j + (0, 1), the extra row h for those outside the image
        # (a negative y & _MASK is above any height)
        y = (torch.add(row0, j, alpha=2) + _constant_steps(j.device, 0)).bitwise_and_(_MASK)
        pix = torch.addcmul(plane, torch.minimum(y, h), row_len) \
            .sub_(torch.addcmul(block_start, q, j), alpha=2)
        return q, (sample.add_(s) if s else sample, torch.addcmul(at, step, j), *pix.unbind(0),
                   fine, phases)

    def chunks(self):
        """``(rows, row (n,), lo, hi, whole)`` per chunk: its slab's rows (:meth:`_slab`),
        each block's row of blocks in them, its blocks lo .. hi − 1, whether they are all
        sampled at whole pixels."""
        for a0, b0, s, t, r0, r1, pieces in self.slabs:
            q, rows = self._slab(a0, b0, s, t, r0, r1)
            for a, b, lo, hi, whole in pieces:
                row = torch.repeat_interleave(q if a == a0 and b == b0 else q[a - a0:b - a0],
                                              output_size=hi - lo)
                if a > a0:
                    row.add_(a - a0)
                yield rows, row, lo, hi, whole


#: Rows of blocks whose numbers the CPU computes at once (see _Plan).
SLAB_ROWS = 1 << 15
#: Sends negative pixel rows above any image's height (see _Plan._slab).
_MASK = (1 << 40) - 1


def _level_rows(grids: Grids) -> list:
    """Per grid level (0 .. :data:`COARSE_MAX_LEVEL`), the numbers its samples need: its last
    column and row w − 1, h − 1, the factor f, h, where its planes' pixel (0, 0) sits, a row's
    and a plane's length in the sums (zeros for a level not drawn). Shape: 7 ints per level."""
    rows = [[0] * 7 for _ in range(COARSE_MAX_LEVEL + 1)]
    for c, offset, h, w, m in grids.levels:
        rows[c] = [w - 1, h - 1, 2 ** c, h, offset + m, w + 2 * m, (h + 1) * (w + 2 * m)]
    return rows


def _on_grid(x: torch.Tensor, f: torch.Tensor) -> torch.Tensor:
    """Image pixel coordinates on a grid ``f`` times coarser: ``(x + 0.5) / f − 0.5``."""
    f = f.to(x.dtype)
    return torch.where(f > 1, (x + 0.5) / f - 0.5, x)


class _Blocks:
    """One chunk of 2 x 2 pixel blocks: their patches, pixels and visibilities.

    Element arrays are (2, 2, n) for n blocks, indexed (patch column j, patch row i, block), so
    that a block's numbers (n,) broadcast along the last, contiguous axis. ``sample`` (n,) the
    block's kept sample; ``per`` (P, n) the per-sample numbers of :func:`_per_sample` for each
    block; ``near`` (2, 2, 2, 2, n): the block's 4 x 4 neighbourhood of the bordered stamp,
    columns and rows 0, 1, P, P + 1 grid points from the block's first (column j P + k and row
    i P + l at ``[j, k, i, l]``; for ``whole`` chunks, P = 1, a view of the 3 x 3 read);
    ``rows`` (2, 2, 2, n): those rows interpolated at the sub-pixel column shift, for patch
    columns j = 0, 1 (row i P + l at ``[j, i, l]``); ``patch`` B; ``pix`` int64 indices into
    the sums (``flat``: flattened); ``vis`` V.
    """

    def __init__(self, plan: _Plan, rows: tuple, row: torch.Tensor, lo: int, hi: int,
                 whole: bool, per: torch.Tensor):
        # (the row's numbers, one gather each)
        self.sample, at, pix0, pix1, stride = (x.index_select(0, row) for x in rows[:5])
        self.per = per.index_select(1, self.sample)
        fu, fv, beta_z, beta = self.per.unbind(0)[:4]
        n = row.numel()
        device = at.device
        two_blocks = torch.arange(2 * lo, 2 * hi, 2, device=device)      # 2 b for block b
        # the block's top-left grid point: patch pixel j of a row mixes the stamp's grid points
        # j P and j P + 1 (from the block's), rows likewise: a 4 x 4 neighbourhood, rows and
        # columns at 0, 1, P, P + 1, read in one gather (as a + b P: column j P + k and row
        # i P + l at [j, k, i, l])
        if whole:   # P = 1: the 3 x 3 of rows and columns 0, 1, 2, each read once, seen as 4 x 4
            rows = torch.addcmul(at + two_blocks, stride, _constant_steps(device, 3))
            near = plan.stamps.pixels.index_select(0, (_constant_steps(device, 4) + rows).view(-1)).view(3, 3, n)
            self.near = near.as_strided((2, 2, 2, 2, n), (3 * n, 3 * n, n, n, 1))
        else:
            phases = rows[5].index_select(0, row)
            ab = torch.addcmul(_constant_steps(device, 5), _constant_steps(device, 6), phases)
            rows = torch.addcmul(torch.addcmul(at, two_blocks, phases), stride, ab)
            self.near = plan.stamps.pixels.index_select(0, (ab.view(2, 2, 1, 1, n) + rows).view(-1)).view(2, 2, 2, 2, n)
        # columns first (weight fu: the shift's fraction of a grid step), then rows (fv)
        left, right = self.near.unbind(1)
        self.rows = torch.lerp(right, left, fu)                         # (2 j, 2 i, 2 l, n)
        top, bottom = self.rows.unbind(2)
        self.patch = torch.lerp(bottom, top, fv)
        start = torch.stack((pix0, pix1)).add_(two_blocks)                  # (2 i, n)
        self.pix = start + _constant_steps(device, 2)                  # (2 j, 2 i, n)
        self.flat = self.pix.view(-1)
        depth = plan.scene.index_select(0, self.flat).view(2, 2, n)
        # V = 1 / (1 + exp(β d − β D)): exp and a reciprocal, whose bits do not depend on an
        # element's place in the tensor (the CPU's sigmoid kernel rounds its tail differently).
        # The exponent is clamped to ±VISIBILITY_CLAMP: V is then off by at most 4e-18, and
        # float32's exp stays on its fast path (and products stay clear of denormals).
        self.vis = torch.addcmul(beta_z, depth, beta, value=-1) \
            .clamp_(-VISIBILITY_CLAMP, VISIBILITY_CLAMP).exp_().add_(1).reciprocal_()


_STEPS: dict = {}


def _constant_steps(device, kind: int = 2) -> torch.Tensor:
    """Small constant arrays, each made once per device: ``kind`` 0, the pixel rows 0, 1 of a
    row of blocks, (2, 1); 2, the patch columns 0, 1, (2, 1, 1); 3 and 4, the rows and the
    columns 0, 1, 2 of a 3 x 3 neighbourhood, (3, 1) and (3, 1, 1); 5 and 6, the rows 0, 1, P,
    P + 1 of a block's neighbourhood as ``a + b P``: a (2, 2, 1) = ((0, 1), (0, 1)), b =
    ((0, 0), (1, 1))."""
    key = (str(device), kind)
    if key not in _STEPS:
        table = {0: [[0], [1]], 2: [[[0]], [[1]]], 3: [[0], [1], [2]], 4: [[[0]], [[1]], [[2]]],
                 5: [[[0], [1]], [[0], [1]]], 6: [[[0], [0]], [[1], [1]]]}
        _STEPS[key] = torch.tensor(table[kind], device=device)
    return _STEPS[key]


def _block_sum(x: torch.Tensor) -> torch.Tensor:
    """Sum over a block's four pixels in a fixed order. Shape: (2, 2, n) -> (n,)."""
    return (x[0, 0] + x[0, 1]) + (x[1, 0] + x[1, 1])


class _Splat(torch.autograd.Function):
    """Scatter-add every kept blur sample's weighted patch into ``A = Σ θ B V`` and
    ``C_c = Σ γ_c θ B V``.

    The forward pass keeps nothing per patch pixel; the backward pass recomputes each chunk and
    applies the chain rule by hand. Shape: u, v, z, theta (I,), color (I, C) -> (1 + C, N)
    (C = 3 colours, or 4 with the depth of a layered render).
    """

    @staticmethod
    def forward(ctx, u, v, z, theta, color, plan: _Plan):
        channels = 1 + color.shape[1]
        acc = torch.zeros(channels, plan.grids.size, dtype=plan.dtype, device=plan.scene.device)
        ctx.plan = plan
        ctx.save_for_backward(u, v, z, theta, color)
        if plan.count == 0:
            return acc
        per, _ = _per_sample(plan, u, v, z, theta, color, weights=True)
        for chunk in plan.chunks():
            b = _Blocks(plan, *chunk, per)
            weight = b.patch.mul_(b.vis)
            # all channels in one product and one scatter along the rows of acc: each sum
            # still receives its additions one by one in the blocks' order
            terms = weight * b.per[4:4 + channels].view(channels, 1, 1, -1)  # (1 + C, 2, 2, n)
            acc.scatter_add_(1, b.flat.expand(channels, -1),
                             terms.view(channels, -1))
        return acc

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_acc):
        u, v, z, theta, color = ctx.saved_tensors
        plan = ctx.plan
        need = ctx.needs_input_grad[:5]
        grads = [torch.zeros_like(t) if n else None for t, n in zip((u, v, z, theta, color), need)]
        if plan.count == 0 or not any(need):
            return (*grads, None)
        nc = color.shape[1] - plan.passive           # (the passive sums pass no gradient)
        per, th = _per_sample(plan, u, v, z, theta, color[:, :nc], weights=False)
        g_acc = g_acc[:1 + nc].contiguous()
        sums = torch.zeros(4 + nc, plan.count, dtype=u.dtype, device=u.device)
        for chunk in plan.chunks():
            b = _Blocks(plan, *chunk, per)
            fv, beta, gamma = b.per[1], b.per[3], b.per[4:4 + nc]
            g = g_acc.index_select(1, b.flat).view(1 + nc, *b.pix.shape).unbind(0)
            # dL/d(θ B V) per pixel: the opacity sum's and the colour sums' gradients
            g_w = torch.addcmul(g[0], g[1], gamma[0])
            for c in range(1, nc):
                g_w.addcmul_(g[1 + c], gamma[c])
            g_bv = g_w.mul_(b.vis)                               # dL/d(θ B) per pixel
            out = [None] * (4 + nc)
            if need[0]:   # dB/dfu: the column difference of the stamp, interpolated in fv
                top, bottom = (b.near[:, 0] - b.near[:, 1]).unbind(2)
                d_fu = torch.lerp(bottom, top, fv)
                out[0] = _block_sum(d_fu.mul_(g_bv))
            if need[1]:   # dB/dfv: the row difference of the interpolated rows
                top, bottom = b.rows.unbind(2)
                d_fv = top - bottom
                out[1] = _block_sum(d_fv.mul_(g_bv))
            g_bvp = g_bv * b.patch                               # dL/dθ per pixel
            if need[2]:   # dV/dd = −β V (1 − V)
                out[2] = _block_sum(g_bvp - g_bvp * b.vis) * beta
            if need[3]:
                out[3] = _block_sum(g_bvp)
            if need[4]:
                bv = b.patch.mul_(b.vis)
                for c in range(nc):
                    out[4 + c] = _block_sum(g[1 + c].mul_(bv))
            for k, value in enumerate(out):
                if value is not None:
                    sums[k].index_add_(0, b.sample, value)
        index = plan.kept
        # d(fraction of a grid step) / du = P / f (P phases, a grid f times coarser)
        scale = th * plan.phases
        if plan.coarse:
            scale = scale / plan.factor
        if need[0]:
            grads[0].index_add_(0, index, scale * sums[0])
        if need[1]:
            grads[1].index_add_(0, index, scale * sums[1])
        if need[2]:
            grads[2].index_add_(0, index, -th * sums[2])
        if need[3]:
            grads[3].index_add_(0, index, sums[3])
        if need[4]:
            grads[4][:, :nc].index_add_(0, index, (th[:, None] * sums[4:].t()))
        return (*grads, None)


def _per_sample(plan: _Plan, u, v, z, theta, color, *,
                weights: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """Per kept sample, packed (4 + C + ``weights``, K), what each block gathers: fu, fv (the
    sub-pixel shift on its grid, as a fraction of the stamp's grid step 1 / P:
    ``P f − floor(P f)``), β d, β, then with ``weights`` (the forward pass) the weights of the
    1 + C sums θ, θ γ_1 .. θ γ_C, else (the backward pass) the colour γ (C); and θ / K (K,)."""
    kept = plan.kept
    beta = plan.beta.index_select(0, kept).to(u.dtype)
    th = theta.index_select(0, kept)
    col = color.index_select(0, kept).t()
    head = (plan.fraction, torch.stack((beta * z.index_select(0, kept), beta)))
    if weights:
        return torch.cat((*head, th[None], th * col)), th
    return torch.cat((*head, col)), th
