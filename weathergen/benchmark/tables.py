"""The benchmark's results, read back from every run's ``summary.json``, and the paper's tables.

Files written into the benchmark folder (all atomically)::

    OUT/results.csv     one row per cell: network, kind, label, pairs, the mean figures, checkpoint
    OUT/results.json    the same rows, plus the networks (checkpoint and sha256), the input
                        selection and the weathergen version
    OUT/tables.md       the three tables in Markdown
    OUT/tables.tex      the same in LaTeX (booktabs), in the layout of the paper's tables

Tables (AEE(f, f̌) in pixels, mean over the pairs; rows × one column per network; the largest
value of each column — the worst robustness — in bold, as in the paper):

- ``augmentations``: random weather per preset (``aee_random`` of the weather cell);
- ``weatherattacks``: adversarial weather per preset (``aee_adversarial``);
- ``of_attacks``: PCFA, I-FGSM and adversarial snow (``aee_adversarial``).

A cell not finished (yet) shows ``–`` and counts for no bold mark.
"""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path
from typing import Optional, Sequence

from .. import __version__
from ..attack.figures import FIGURE_KEYS
from ..io.atomic import atomic_write_bytes
from .grid import BenchmarkSpec, checkpoint_record

FIGURES = ("aee_random", "aee_adversarial", "target_initial", "target_adversarial",
           "epe_benign", "epe_random", "epe_adversarial") + FIGURE_KEYS
COLUMNS = ("network", "kind", "label", "pairs") + FIGURES + ("checkpoint", "sha256", "folder")
LP_NAMES = {"pcfa": "PCFA", "ifgsm": "I-FGSM"}
TABLES = {
    "augmentations": "Robustness AEE(f, f̌) of random weather (augmentations)",
    "weatherattacks": "Robustness AEE(f, f̌) of adversarial weather",
    "of_attacks": "Robustness AEE(f, f̌) under different attacks",
}

LATEX_CAPTIONS = {
    "augmentations": r"Robustness AEE$(f,\check{f})$ of random weather (augmentations).",
    "weatherattacks": r"Robustness AEE$(f,\check{f})$ of adversarial weather.",
    "of_attacks": r"Robustness AEE$(f,\check{f})$ under different attacks.",
}


def collect_results(spec: BenchmarkSpec) -> list[dict]:
    """One row per cell of the whole grid, its figures read from the cell's ``summary.json``
    (None where the cell has not finished)."""
    rows = []
    records = {net: checkpoint_record(net, spec.checkpoints.get(net)) for net in spec.networks}
    for cell in spec.cells():
        folder = cell.folder(spec.out)
        summary = _read_summary(folder)
        row = {"network": cell.network, "kind": cell.kind, "label": cell.label,
               "pairs": summary.get("pairs") if summary else None}
        for key in FIGURES:
            row[key] = summary.get(key) if summary else None
        row.update(checkpoint=records[cell.network]["checkpoint"],
                   sha256=records[cell.network]["sha256"],
                   folder=str(folder.relative_to(spec.out)))
        rows.append(row)
    return rows


def _read_summary(folder: Path) -> Optional[dict]:
    path = folder / "summary.json"
    if not path.is_file():
        return None
    return json.loads(path.read_text())


def table_rows(rows: list[dict], networks: Sequence[str], name: str) -> list[tuple[str, list]]:
    """``[(row label, [value per network])]`` of one of :data:`TABLES`."""
    def value(kind, label, net, key):
        for r in rows:
            if (r["network"], r["kind"], r["label"]) == (net, kind, label):
                return r[key]
        return None

    weather = [r["label"] for r in rows if r["kind"] == "weather" and r["network"] == networks[0]]
    lp = [r["label"] for r in rows if r["kind"] == "lp" and r["network"] == networks[0]]
    if name == "augmentations":
        return [(p, [value("weather", p, n, "aee_random") for n in networks]) for p in weather]
    if name == "weatherattacks":
        return [(p, [value("weather", p, n, "aee_adversarial") for n in networks])
                for p in weather]
    out = [(LP_NAMES.get(m, m), [value("lp", m, n, "aee_adversarial") for n in networks])
           for m in lp]
    if "snow" in weather:
        out.append(("Snow (ours)", [value("weather", "snow", n, "aee_adversarial")
                                    for n in networks]))
    return out


def _worst(body: list[tuple[str, list]]) -> list[Optional[float]]:
    cols = list(zip(*[values for _, values in body])) if body else []
    return [max((v for v in col if v is not None), default=None) for col in cols]


def _fmt(v, worst, bold) -> str:
    if v is None:
        return "–"
    text = f"{v:.2f}"
    return bold(text) if worst is not None and v == worst else text


def markdown_table(name: str, body, networks: Sequence[str]) -> str:
    worst = _worst(body)
    head = "Attack" if name == "of_attacks" else "Weather"
    lines = [f"### {name}: {TABLES[name]}", "",
             "| " + " | ".join([head, *networks]) + " |",
             "| " + " | ".join(["---"] + ["---:"] * len(networks)) + " |"]
    for label, values in body:
        cells = [_fmt(v, w, lambda t: f"**{t}**") for v, w in zip(values, worst)]
        lines.append("| " + " | ".join([label, *cells]) + " |")
    return "\n".join(lines) + "\n"


def latex_table(name: str, body, networks: Sequence[str]) -> str:
    worst = _worst(body)
    head = "Attack" if name == "of_attacks" else "Weather"
    esc = lambda s: str(s).replace("_", r"\_").replace("%", r"\%")   # noqa: E731
    cols = " & ".join(r"\multicolumn{1}{c}{\rotatebox{45}{" + esc(n) + "}}" for n in networks)
    lines = [r"\begin{table}", r"\small", r"\begin{center}",
             r"\begin{tabular}{l" + "r" * len(networks) + "}", r"\toprule",
             f"{head} & {cols} \\\\", r"\midrule"]
    for label, values in body:
        cells = [_fmt(v, w, lambda t: r"\textbf{" + t + "}") for v, w in zip(values, worst)]
        lines.append(" & ".join([esc(label), *cells]) + r" \\")
    lines += [r"\bottomrule", r"\end{tabular}",
              r"\caption{" + LATEX_CAPTIONS[name] + r" Worst robustness bold.}",
              r"\label{table:" + name + "}", r"\end{center}", r"\end{table}"]
    return "\n".join(lines) + "\n"


def write_tables(spec: BenchmarkSpec) -> dict[str, Path]:
    """Collect every cell's figures and write results.csv/json and tables.md/tex; return paths."""
    rows = collect_results(spec)
    networks = list(spec.networks)
    out = Path(spec.out)
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=COLUMNS, lineterminator="\n")
    writer.writeheader()
    for r in rows:
        writer.writerow({k: ("" if r[k] is None else r[k]) for k in COLUMNS})
    document = {"weathergen_version": __version__, "input": spec.dataset.describe(),
                "seed": spec.seed,
                "networks": [checkpoint_record(n, spec.checkpoints.get(n)) for n in networks],
                "settings": {"weather_steps": spec.steps, "lp_steps": spec.lp_steps,
                             "iters": spec.iters, "overrides": dict(spec.overrides),
                             "compat": spec.compat},
                "rows": rows}
    bodies = {name: table_rows(rows, networks, name) for name in TABLES}
    md = "\n".join(markdown_table(n, b, networks) for n, b in bodies.items())
    tex = "\n".join(latex_table(n, b, networks) for n, b in bodies.items())
    paths = {"csv": out / "results.csv", "json": out / "results.json",
             "markdown": out / "tables.md", "latex": out / "tables.tex"}
    atomic_write_bytes(paths["csv"], buf.getvalue().encode())
    atomic_write_bytes(paths["json"], (json.dumps(document, indent=2, sort_keys=True) + "\n").encode())
    atomic_write_bytes(paths["markdown"], md.encode())
    atomic_write_bytes(paths["latex"], tex.encode())
    return paths
