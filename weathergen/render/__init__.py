"""The render job: weather rendered into every selected pair of a dataset, written to a folder.

- :mod:`.particles`: which particles a pair gets (its own seed, or an earlier output's);
- :mod:`.shards`: splitting a run over job arrays;
- :mod:`.job`: the run itself (workers, batches, resumption, the manifest), writing through
  :mod:`weathergen.outputs`;
- :mod:`.preview`: contact sheets of a finished render.
"""

from __future__ import annotations

from .job import (RENDER_THREADS, PairResult, RenderJob, prepare_output, record_run, render_batch,
                  run_render)
from .particles import pair_particles, pair_seed
from .preview import contact_sheet
from .shards import parse_shard, shard_refs

__all__ = ["RENDER_THREADS", "PairResult", "RenderJob", "contact_sheet", "pair_particles",
           "pair_seed", "parse_shard", "prepare_output", "record_run", "render_batch",
           "run_render", "shard_refs"]
