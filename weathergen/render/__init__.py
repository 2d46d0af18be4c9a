"""The render job: weather rendered into every selected pair of a dataset, written to a folder.

- which particles a pair gets (its own seed, or an earlier output's) is
  :mod:`weathergen.jobs`, shared with the attack job;
- :mod:`.shards`: splitting a run over job arrays;
- :mod:`.job`: the run itself (workers, batches), writing through :mod:`weathergen.outputs`;
  :mod:`.bookkeeping`: which files a pair has (resumption, clean-up) and the manifest;
- :mod:`.plan`: the rules that turn a request into a job (which preset, which settings win);
- :mod:`.preview`: contact sheets of a finished render; :mod:`.video`: videos of one.
"""

from __future__ import annotations

from .bookkeeping import record_run
from .job import RENDER_THREADS, PairResult, RenderJob, render_batch, run_render
from ..jobs.particles import pair_particles, pair_seed
from .plan import (APPEARANCE_KEYS, ResolvedPreset, default_batch_size, default_out,
                   default_pass_name, published_preset, resolve_preset)
from .preview import contact_sheet
from .shards import parse_shard, shard_refs
from .video import VideoPreview, output_frame_rate, video_preview

__all__ = ["APPEARANCE_KEYS", "RENDER_THREADS", "ResolvedPreset", "default_batch_size",
           "default_out", "default_pass_name", "resolve_preset", "PairResult", "RenderJob",
           "contact_sheet", "pair_particles", "published_preset",
           "pair_seed", "parse_shard", "record_run", "render_batch",
           "run_render", "shard_refs", "VideoPreview", "output_frame_rate", "video_preview"]
