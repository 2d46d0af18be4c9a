"""The paper's tables in one command: a grid of attack runs and the tables made from them.

- :mod:`.grid`: the cells (networks × presets × Lp methods), their attack jobs, shards, and
  :func:`run_grid` (the place an executor plugs in);
- :mod:`.tables`: the results read back from every run's ``summary.json``, written as CSV, JSON,
  Markdown and LaTeX in the layout of the paper's tables;
- :mod:`.ladder`: severity ladders (light, moderate, heavy presets of one weather), the curve
  of each network over them and the robustness scores;
- :mod:`.plot`: a bar chart of AEE(f, f̌) per network and preset, the ladders' curves (PNG).
"""

from __future__ import annotations

from .grid import (DEFAULT_LP, DEFAULT_PRESETS, TR115_FRAMES_PER_SCENE, BenchmarkSpec, Cell,
                   cell_job, checkpoint_record, label_config, run_grid, shard_cells, tr115_default)
from .ladder import (MODES, RUNGS, Curve, available_ladders, curve_rows, ladder_curves, ladder_presets,
                     score_rows)
from .plot import draw_aee, draw_chart, draw_ladder, draw_ladder_chart
from .tables import (build_tables, collect_results, ladder_tables, latex_table, markdown_table,
                     table_networks, write_tables)

__all__ = ["DEFAULT_LP", "DEFAULT_PRESETS", "TR115_FRAMES_PER_SCENE", "BenchmarkSpec", "Cell",
           "build_tables", "cell_job", "checkpoint_record", "collect_results", "draw_aee",
           "draw_chart", "label_config", "latex_table", "markdown_table", "run_grid", "shard_cells",
           "tr115_default", "write_tables", "MODES", "RUNGS", "Curve", "available_ladders",
           "curve_rows", "draw_ladder", "draw_ladder_chart", "ladder_curves", "ladder_presets",
           "ladder_tables", "score_rows", "table_networks"]
