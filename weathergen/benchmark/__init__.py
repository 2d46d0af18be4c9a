"""The paper's tables in one command: a grid of attack runs and the tables made from them.

- :mod:`.grid`: the cells (networks × presets × Lp methods), their attack jobs, shards, and
  :func:`run_grid` (the place an executor plugs in);
- :mod:`.tables`: the results read back from every run's ``summary.json``, written as CSV, JSON,
  Markdown and LaTeX in the layout of the paper's tables.
"""

from __future__ import annotations

from .grid import (DEFAULT_LP, DEFAULT_PRESETS, TR115_FRAMES_PER_SCENE, BenchmarkSpec, Cell,
                   cell_job, checkpoint_record, run_grid, shard_cells, tr115_default)
from .tables import collect_results, write_tables

__all__ = ["DEFAULT_LP", "DEFAULT_PRESETS", "TR115_FRAMES_PER_SCENE", "BenchmarkSpec", "Cell",
           "cell_job", "checkpoint_record", "collect_results", "run_grid", "shard_cells",
           "tr115_default", "write_tables"]
