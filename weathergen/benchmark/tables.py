"""The benchmark's results, read back from every run's ``summary.json``, and the paper's tables.

Files written into the benchmark folder (all atomically)::

    OUT/results.csv         one row per cell: network, kind, label, pairs, the mean figures, the
                            attack mode and mixed precision it ran with, checkpoint
    OUT/results.json        the same rows, plus the networks (checkpoint and sha256), the input
                            selection, the settings and the weathergen version
    OUT/tables.md           every table in Markdown
    OUT/tables.tex          every table in LaTeX, a document that compiles on its own (graphicx;
                            booktabs where installed, plain rules otherwise)
    OUT/tables/NAME.md      one table per file, Markdown
    OUT/tables/NAME.tex     one table per file, a LaTeX ``table`` float to ``\\input``
    OUT/aee.png             AEE(f, f̌) per network and preset, random and adversarial (:mod:`.plot`)
    OUT/ladders.csv         with ladders: every curve (:mod:`.ladder`), one row per point
    OUT/robustness.csv      with ladders: the scores R and RCE per ladder, network and mode
    OUT/ladder.png          with ladders: the curves (:func:`~.plot.draw_ladder`)

One table per table of the paper that the grid's cells fill, numbered and laid out as the paper's
(AEE(f, f̌) in pixels, mean over the pairs; networks as columns in the paper's order, named as it
names them: FN2, FNCR, SpyNet, RAFT, GMA, FF, then the other networks in the order given; rows in
the paper's order, others after them; the worst, i.e. largest, value of each column bold, of each
family in Table 2):

- ``augmentations`` (the paper's Table 2; on KITTI its supplement's KITTI table): the random
  weather of every preset cell (``aee_random``), the paper's families (particles, motion blur,
  colour, size) grouped under their headings in the paper's order, the main augmentations in
  their families' rows as the paper highlights them (snow is ``3000 (snow)`` of Particles, rain
  ``0.15 (rain)`` of Motion blur, sparks ``red (sparks)`` of Color additive, fog ``fog`` of Size),
  the worst of each family bold, as the paper marks it (rows alone in their section are ranked
  with one another); presets outside the families last;
- ``optimvariables`` (Table 3): the attack-configuration cells (e.g. ``grey-offset1``), one row
  per set of freed variables in the paper's three sections, under an ``Initial`` row (the random
  weather, not ranked); the second worst underlined;
- ``weatherattacks`` (Table 4): the adversarial figure of every preset cell (snow, rain, sparks,
  fog first);
- ``of_attacks`` (Table 5): the Lp baselines (PCFA, I-FGSM) beside the adversarial snow.

A table whose cells the grid does not have is left out; a cell not finished (yet) shows ``–`` and
counts for no mark. With ladders, two tables per ladder follow (:func:`ladder_tables`).
"""

from __future__ import annotations

import csv
import io
import json
import unicodedata
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

from .. import __version__
from ..attack.figures import FIGURE_KEYS
from ..attack.record import settings_text
from ..io.atomic import atomic_write_bytes
from ..outputs import read_summary
from .grid import BenchmarkSpec, checkpoint_record, label_config, network_name
from .ladder import MODES, Curve, curve_rows, ladder_curves, score_rows
from .plot import draw_aee, draw_ladder

FIGURES = ("aee_random", "aee_adversarial", "target_initial", "target_adversarial",
           "epe_benign", "epe_random", "epe_adversarial") + FIGURE_KEYS
#: The settings record's entries each row of ``results.csv`` carries
#: (:func:`~weathergen.attack.record.run_settings`; the network and checkpoint have their columns).
SETTINGS_COLUMNS = ("iters", "precision", "padding", "crop", "steps", "learning_rates", "seed")
COLUMNS = ("network", "kind", "label", "pairs") + FIGURES + ("compat", "amp", "checkpoint",
                                                               "sha256") + SETTINGS_COLUMNS + ("folder",)
LP_NAMES = {"pcfa": "PCFA", "ifgsm": "I-FGSM"}
#: The columns of ``ladders.csv`` (the curves) and ``robustness.csv`` (the scores).
CURVE_COLUMNS = ("ladder", "network", "mode", "point", "label", "aee", "epe")
SCORE_COLUMNS = ("ladder", "network", "mode", "epe_clean", "robustness", "relative_error",
                 "rungs_done", "rungs")
#: The families of the paper's Table 1: preset-name prefix, heading (Markdown, LaTeX).
FAMILIES = (("particles-", "Particles", "Particles"),
            ("motion-blur-", "Motion blur", "Motion blur"),
            ("additive-", "Color additive", "Color additive"),
            ("alpha-", "Color α-blending", r"Color $\alpha$-blending"),
            ("size-", "Size", "Size"))
#: The paper's main augmentations are rows of its Table 1's families (highlighted there): each is
#: the family member of the same settings (tested), so it is shown in that family's row.
MAIN_ROWS = {"snow": "particles-3000", "rain": "motion-blur-0.15", "sparks": "additive-red",
             "fog": "size-fog"}
#: The rows of each family of the paper's Table 2, in its order (the part after the prefix).
FAMILY_ROWS = {"particles-": ("1000", "2000", "3000", "4000", "5000"),
               "motion-blur-": ("0.0", "0.0375", "0.075", "0.1125", "0.15"),
               "additive-": ("white", "red", "green", "blue", "color"),
               "alpha-": ("white", "red", "green", "blue", "color"),
               "size-": ("small", "medium", "large", "fog")}
#: The rows of the paper's Table 4 (adversarial weather), in its order.
WEATHER_ROWS = ("snow", "rain", "sparks", "fog")
#: The sets of freed variables of the paper's Table 3, in its order, in its three sections (one
#: variable, two, all).
VARIABLE_SECTIONS = ((("offset1",), ("offset2",), ("color",), ("transparency",)),
                     (("offset1", "offset2"), ("color", "transparency")),
                     (("offset1", "offset2", "color", "transparency"),))
#: The Lp attacks of the paper's Table 5, in its order.
LP_ROWS = ("pcfa", "ifgsm")
#: The paper's six networks, in the order of its tables' columns.
PAPER_NETWORKS = ("flownet2", "flownetcrobust", "spynet", "raft", "gma", "flowformer")
#: The freed variables as the paper writes them (Markdown, LaTeX).
SYMBOLS = {"offset1": ("1", "1"), "offset2": ("2", "2"), "color": ("c", "c"),
           "transparency": ("θ", r"\theta")}
#: The number of each table in the paper.
TABLE_NUMBERS = {"augmentations": 2, "optimvariables": 3, "weatherattacks": 4, "of_attacks": 5}
#: The tables, in the paper's order: (Markdown title, LaTeX caption).
TABLES = {
    "augmentations": ("Robustness AEE(f, f̌) ↓ of random weather (augmentations)",
                      r"Robustness AEE$(f,\check{f})$ $\downarrow$ of random particle-based "
                      r"weather (augmentations)"),
    "optimvariables": ("Adversarial robustness AEE(f, f̌) ↓ of particles optimised in "
                       "different variables",
                       r"Adversarial robustness AEE$(f,\check{f})$ $\downarrow$ of particles "
                       r"optimised in different variables"),
    "weatherattacks": ("Adversarial robustness AEE(f, f̌) ↓ for adversarial weather",
                       r"Adversarial robustness AEE$(f,\check{f})$ $\downarrow$ for adversarial "
                       r"weather"),
    "of_attacks": ("Adversarial robustness AEE(f, f̌) ↓ for different attacks",
                   r"Adversarial robustness AEE$(f,\check{f})$ $\downarrow$ for different "
                   r"attacks"),
}


# -- reading the results -------------------------------------------------------------------------

def collect_results(spec: BenchmarkSpec) -> list[dict]:
    """One row per cell of the whole grid, its figures read from the cell's ``summary.json``
    (None where the cell has not finished)."""
    rows = []
    records = {net: checkpoint_record(spec, net) for net in spec.networks}
    for cell in spec.cells():
        folder = cell.folder(spec.out)
        summary = read_summary(folder)
        row = {"network": cell.network, "kind": cell.kind, "label": cell.label,
               "pairs": summary.get("pairs") if summary else None}
        for key in FIGURES:
            row[key] = summary.get(key) if summary else None
        settings = (summary or {}).get("settings") or {}
        row.update(compat=summary.get("compat") if summary else None,
                   amp=summary.get("amp") if summary else None,
                   checkpoint=records[cell.network]["checkpoint"],
                   sha256=records[cell.network]["sha256"] or settings.get("checkpoint_sha256"),
                   **{key: settings.get(key) for key in SETTINGS_COLUMNS},
                   folder=str(folder.relative_to(spec.out)))
        if row["learning_rates"]:
            row["learning_rates"] = ";".join(f"{k}={v:g}" for k, v in row["learning_rates"].items())
        row["settings"] = settings or None
        rows.append(row)
    return rows


def _with_settings(table_rows: list[dict], rows: Sequence[dict]) -> list[dict]:
    """Rows of a ladder's curves or scores with their network's settings (of its weather cells)."""
    of = {}
    for r in rows:
        if r["kind"] == "weather" and r.get("settings"):
            of.setdefault(r["network"], r)
    return [{**t, **{k: of.get(t["network"], {}).get(k) for k in SETTINGS_COLUMNS}}
            for t in table_rows]


# -- the tables as data --------------------------------------------------------------------------

@dataclass
class Row:
    """One row: its label (Markdown, LaTeX) and one value per column; ``ranked`` rows take part
    in the bold (worst) and underline (second worst) marks."""

    label: str
    label_tex: str
    values: list
    ranked: bool = True
    #: columns whose cell is marked † (a ladder's adversarial rung below its random one)
    flagged: tuple = ()


@dataclass
class Table:
    """A table: ``columns`` (one per value; Markdown headers), grouped under ``groups`` (header,
    span) when each network has several columns; ``sections`` of rows, each under an optional
    heading (Markdown, LaTeX)."""

    name: str
    head: str
    columns: list
    sections: list = field(default_factory=list)
    groups: Optional[list] = None
    underline_second: bool = False
    #: rank within each section of several rows (the paper's Table 2 marks the worst of each
    #: family), the rows of one-row sections with one another, rather than over the whole table
    rank_by_section: bool = False
    note: str = ""
    #: the table's number in the paper (None: a table the paper does not have)
    number: Optional[int] = None

    def rows(self) -> list[Row]:
        return [row for _, rows in self.sections for row in rows]

    def marks(self) -> dict:
        """``{(row id, column): "bold" | "underline"}`` over the ranked rows of each column (of
        each section, with ``rank_by_section``)."""
        out = {}
        if self.rank_by_section:
            groups = [rows for _, rows in self.sections if len(rows) > 1]
            groups.append([row for _, rows in self.sections if len(rows) == 1 for row in rows])
        else:
            groups = [self.rows()]
        for group in groups:
            ranked = [r for r in group if r.ranked]
            for c in range(len(self.columns)):
                values = sorted({r.values[c] for r in ranked if r.values[c] is not None},
                                reverse=True)
                for r in ranked:
                    v = r.values[c]
                    if values and v == values[0]:
                        out[(id(r), c)] = "bold"
                    elif self.underline_second and len(values) > 1 and v == values[1]:
                        out[(id(r), c)] = "underline"
        return out


def _lookup(rows: list[dict]):
    index = {(r["network"], r["kind"], r["label"]): r for r in rows}
    return lambda net, kind, label, key: (index.get((net, kind, label)) or {}).get(key)


def _family(label: str):
    """``((heading, heading_tex), row label, position)`` of a preset in the paper's Table 2, or
    ``(None, label, 0)`` for a preset outside its families; a main augmentation (snow, rain,
    sparks, fog) is its family's row, named as both (``3000 (snow)``). ``position``: the row's
    place in the paper's family."""
    member = MAIN_ROWS.get(label, label)
    for prefix, heading, heading_tex in FAMILIES:
        if member.startswith(prefix) and len(member) > len(prefix):
            short = member[len(prefix):]
            order = FAMILY_ROWS.get(prefix, ())
            position = order.index(short) if short in order else len(order)
            shown = short if short == label or member == label else f"{short} ({label})"
            return (heading, heading_tex), shown, position
    return None, label, 0


def in_paper_order(labels: Sequence[str], order: Sequence) -> list[str]:
    """``labels`` sorted as ``order`` lists them; the others after, as given."""
    rank = {name: i for i, name in enumerate(order)}
    return sorted(labels, key=lambda x: (rank.get(x, len(rank)),
                                         list(labels).index(x) if x not in rank else 0))


def table_networks(networks: Sequence[str]) -> list[str]:
    """The networks as the paper's tables order them: FN2, FNCR, SpyNet, RAFT, GMA, FF, then the
    others in the order given."""
    return in_paper_order(list(dict.fromkeys(networks)), PAPER_NETWORKS)


def variables_label(optimize: Sequence[str]) -> tuple[str, str]:
    """The paper's name of a set of freed variables: δ1, δ2, δc, δθ, δ1,2, δc,θ, δall."""
    if len(optimize) == len(SYMBOLS):
        return "δall", r"$\delta_{\mathrm{all}}$"
    md = ",".join(SYMBOLS[v][0] for v in optimize)
    tex = ",".join(SYMBOLS[v][1] for v in optimize)
    return f"δ{md}", f"$\\delta_{{{tex}}}$"


def _variables_section(label: str) -> tuple[int, int]:
    """``(section, position)`` of a configuration's freed variables in the paper's Table 3; the
    variable sets it does not have after its sections."""
    freed = tuple(sorted(label_config(label).optimize))
    for i, section in enumerate(VARIABLE_SECTIONS):
        for j, variables in enumerate(section):
            if tuple(sorted(variables)) == freed:
                return i, j
    return len(VARIABLE_SECTIONS), 0


def build_tables(rows: list[dict], networks: Sequence[str],
                 presets: Optional[Sequence[str]] = None) -> list[Table]:
    """The tables the grid's cells fill, numbered, ordered and laid out as the paper's: its
    networks in its order (others after them), its rows in its order (others after them).
    ``presets``: the weather labels that go into the paper's tables (default: every weather
    cell's; a ladder's rungs that are not among them stay in the ladder's tables)."""
    value = _lookup(rows)
    networks = table_networks(networks)
    first = networks[0]
    weather = [r["label"] for r in rows if r["kind"] == "weather" and r["network"] == first
               and (presets is None or r["label"] in presets)]
    configs = [label for label in weather if label_config(label) is not None]
    plain = [label for label in weather if label_config(label) is None]
    lp = in_paper_order([r["label"] for r in rows if r["kind"] == "lp" and r["network"] == first],
                        LP_ROWS)
    names = [network_name(n) for n in networks]
    tables = []
    if plain:
        tables.append(_augmentations(plain, networks, names, value))
    if configs:
        tables.append(_optimvariables(configs, networks, names, value))
    if plain:
        body = [Row(label, latex_text(label),
                    [value(n, "weather", label, "aee_adversarial") for n in networks])
                for label in in_paper_order(plain, WEATHER_ROWS)]
        tables.append(Table("weatherattacks", "Attack", names, sections=[(None, body)],
                            number=TABLE_NUMBERS["weatherattacks"]))
    if lp:
        body = [Row(LP_NAMES.get(m, m), latex_text(LP_NAMES.get(m, m)),
                    [value(n, "lp", m, "aee_adversarial") for n in networks]) for m in lp]
        if "snow" in plain:
            body.append(Row("Snow (ours)", "Snow (ours)",
                            [value(n, "weather", "snow", "aee_adversarial") for n in networks]))
        tables.append(Table("of_attacks", "Attack", names, sections=[(None, body)],
                            number=TABLE_NUMBERS["of_attacks"]))
    return tables


def _augmentations(presets, networks, names, value) -> Table:
    """The paper's Table 2: the random weather of every preset, by family in the paper's order,
    the presets outside its families last."""
    sections: dict = {}
    for label in presets:
        heading, short, position = _family(label)
        sections.setdefault(heading, []).append(
            (position, Row(short, latex_text(short),
                           [value(n, "weather", label, "aee_random") for n in networks])))
    order = [(h, tex) for _, h, tex in FAMILIES] + [None]              # the paper's order
    return Table("augmentations", "Weather", names, rank_by_section=True,
                 sections=[(h, [row for _, row in sorted(sections[h], key=lambda e: e[0])])
                           for h in order if h in sections],
                 number=TABLE_NUMBERS["augmentations"])


def _optimvariables(configs, networks, names, value) -> Table:
    """The paper's Table 3: ``Initial`` (the random particles, not ranked), then the
    configurations by their freed variables, in its sections and order."""
    initial = [next((v for v in (value(n, "weather", c, "aee_random") for c in configs)
                     if v is not None), None) for n in networks]
    placed: dict = {}
    for label in configs:
        section, position = _variables_section(label)
        md, tex = variables_label(label_config(label).optimize)
        placed.setdefault(section, []).append(
            (position, Row(f"{md} ({label})", f"{tex} ({latex_text(label)})",
                           [value(n, "weather", label, "aee_adversarial") for n in networks])))
    sections = [(None, [Row("Initial", "Initial", initial, ranked=False)])]
    sections += [(None, [row for _, row in sorted(placed[k], key=lambda e: e[0])])
                 for k in sorted(placed)]
    return Table("optimvariables", "Parameters", names, underline_second=True,
                 sections=sections, number=TABLE_NUMBERS["optimvariables"])


#: The remark under a ladder's table whose adversarial rung fell below its random one.
LADDER_BELOW = ("† adversarial below random ({}): the attack ended weaker than the random "
                "weather it started from; its figures at that rung do not bound the network's "
                "robustness (more steps, another learning rate; docs/attack.md).")


def ladder_tables(curves: Sequence[Curve], networks: Sequence[str]) -> list[Table]:
    """Per ladder two tables, one row per network (the paper's order, others after): AEE(f, f̌)
    per rung and the robustness score R, and EPE against the ground truth (clean, per rung) with
    the relative corruption error RCE, random and adversarial weather side by side. An
    adversarial rung below its random one is marked † and named in the table's note."""
    tables = []
    order = table_networks(networks)
    for ladder in dict.fromkeys(c.ladder for c in curves):
        by = {(c.network, c.mode): c for c in curves if c.ladder == ladder}
        rungs = [label.rsplit("-", 1)[-1] for label, _, _ in by[(order[0], "random")].rungs]
        aee, epe, below = [], [], []
        for net in order:
            name = network_name(net)
            pairs = list(zip(by[(net, "random")].rungs, by[(net, "adversarial")].rungs))
            flagged = tuple(len(rungs) + 1 + i for i, ((_, r, _), (_, a, _)) in enumerate(pairs)
                            if r is not None and a is not None and a < r)
            below += [f"{name} {rungs[c - len(rungs) - 1]}" for c in flagged]
            aee.append(Row(name, latex_text(name), [
                v for mode in MODES for v in
                [a for _, a, _ in by[(net, mode)].rungs] + [by[(net, mode)].robustness()]],
                flagged=flagged))
            epe.append(Row(name, latex_text(name), [by[(net, "random")].points[0][2]] + [
                v for mode in MODES for v in
                [e for _, _, e in by[(net, mode)].rungs] + [by[(net, mode)].relative_error()]]))
        short = {"random": "rand.", "adversarial": "adv."}
        tables.append(Table(
            f"ladder_{ladder}", "Network",
            [f"{short[m]} {x}" for m in MODES for x in [*rungs, "R"]],
            sections=[(None, aee)], groups=[(m, len(rungs) + 1) for m in MODES],
            note=LADDER_BELOW.format(", ".join(below)) if below else ""))
        tables.append(Table(
            f"ladder_{ladder}_epe", "Network",
            ["clean EPE"] + [f"{short[m]} {x}" for m in MODES for x in [*rungs, "RCE"]],
            sections=[(None, epe)],
            groups=[("clean", 1)] + [(m, len(rungs) + 1) for m in MODES]))
    return tables


# -- Markdown and LaTeX --------------------------------------------------------------------------

_LATEX_SPECIALS = {"\\": r"\textbackslash{}", "&": r"\&", "%": r"\%", "$": r"\$", "#": r"\#",
                   "_": r"\_", "{": r"\{", "}": r"\}", "~": r"\textasciitilde{}",
                   "^": r"\textasciicircum{}"}


def latex_text(text: str) -> str:
    """``text`` as LaTeX text: special characters escaped, accents dropped and any other
    non-ASCII character replaced by ``?`` (so that plain pdflatex compiles it)."""
    plain = unicodedata.normalize("NFKD", str(text))
    plain = "".join(c for c in plain if not unicodedata.combining(c))
    return "".join(_LATEX_SPECIALS.get(c, c if ord(c) < 128 else "?") for c in plain)


def _markdown_text(text: str) -> str:
    return str(text).replace("|", r"\|")


def _fmt(v) -> str:
    return "–" if v is None else f"{v:.2f}"


def markdown_table(table: Table, caption: str) -> str:
    marks = table.marks()
    wrap = {"bold": lambda t: f"**{t}**", "underline": lambda t: f"<u>{t}</u>"}
    width = len(table.columns) + 1
    title = table.name if table.number is None else f"Table {table.number} ({table.name})"
    lines = [f"### {title}: {caption}", "",
             "| " + " | ".join([table.head, *map(_markdown_text, table.columns)]) + " |",
             "| " + " | ".join(["---"] + ["---:"] * len(table.columns)) + " |"]
    for heading, rows in table.sections:
        if heading is not None:
            lines.append("| " + " | ".join([f"**{heading[0]}**"] + [""] * (width - 1)) + " |")
        for row in rows:
            cells = [_fmt(v) + ("†" if c in row.flagged else "") for c, v in enumerate(row.values)]
            cells = [wrap[marks[(id(row), c)]](t) if (id(row), c) in marks else t
                     for c, t in enumerate(cells)]
            lines.append("| " + " | ".join([_markdown_text(row.label), *cells]) + " |")
    if table.note:
        lines += ["", table.note]
    return "\n".join(lines) + "\n"


def latex_table(table: Table, caption: str) -> str:
    marks = table.marks()
    wrap = {"bold": lambda t: r"\textbf{" + t + "}", "underline": lambda t: r"\underline{" + t + "}"}
    width = len(table.columns) + 1
    lines = [r"\begin{table}", r"\small", r"\begin{center}",
             r"\begin{tabular}{l" + "r" * len(table.columns) + "}", r"\toprule"]
    if table.groups:
        heads, rules, start = [], [], 2
        for name, span in table.groups:
            heads.append(r"\multicolumn{" + str(span) + "}{c}{" + latex_text(name) + "}")
            rules.append(r"\cmidrule(lr){" + f"{start}-{start + span - 1}" + "}")
            start += span
        lines.append(" & ".join([latex_text(table.head), *heads]) + r" \\")
        lines.append(" ".join(rules))
        subs = [c.rsplit(" ", 1)[-1] for c in table.columns]
        lines.append(" & ".join(["", *map(latex_text, subs)]) + r" \\")
    else:
        heads = [r"\multicolumn{1}{c}{\rotatebox{45}{" + latex_text(c) + "}}" for c in table.columns]
        lines.append(" & ".join([latex_text(table.head), *heads]) + r" \\")
    for heading, rows in table.sections:
        lines.append(r"\midrule")
        if heading is not None:
            lines.append(r"\multicolumn{" + str(width) + r"}{l}{\emph{" + heading[1] + r"}} \\")
        for row in rows:
            cells = [_fmt(v).replace("–", "--") + (r"$^\dagger$" if c in row.flagged else "")
                     for c, v in enumerate(row.values)]
            cells = [wrap[marks[(id(row), c)]](t) if (id(row), c) in marks else t
                     for c, t in enumerate(cells)]
            lines.append(" & ".join([row.label_tex, *cells]) + r" \\")
    lines += [r"\bottomrule", r"\end{tabular}"]
    if table.note:
        lines.append(r"\par\footnotesize " + r"$\dagger$".join(map(latex_text,
                                                                   table.note.split("†"))))
    lines += [r"\caption{" + caption + "}",
              r"\label{table:" + table.name + "}", r"\end{center}", r"\end{table}"]
    return "\n".join(lines) + "\n"


#: The document around the tables in ``tables.tex``: booktabs rules where the package is
#: installed, plain ``\hline``/``\cline`` otherwise, so that a bare LaTeX compiles it too.
LATEX_PREAMBLE = "\n".join([
    r"\documentclass{article}",
    r"\usepackage{graphicx}",
    r"\IfFileExists{booktabs.sty}{\usepackage{booktabs}}{%",
    r"  \newcommand{\toprule}{\hline}\newcommand{\midrule}{\hline}%",
    r"  \newcommand{\bottomrule}{\hline}\def\cmidrule(##1)##2{\cline{##2}}}",
    r"\begin{document}", ""])


def captions(spec: BenchmarkSpec, tables: Sequence[Table] = ()) -> dict[str, tuple[str, str]]:
    """Each table's caption (Markdown, LaTeX), naming the input and the attack mode; the ladder
    tables among ``tables`` too."""
    where = spec.dataset.describe()
    name = f"{where.get('dataset', 'dataset')} {where.get('split', '')}".strip()
    mode = "" if spec.compat == "paper" else f" Research code's attack terms (--compat {spec.compat})."
    mode_tex = "" if spec.compat == "paper" else \
        f" Research code's attack terms (\\texttt{{--compat {latex_text(spec.compat)}}})."
    out = {key: (f"{md} on {name}, worst robustness bold.{mode}",
                 f"{tex} on {latex_text(name)}, worst robustness bold.{mode_tex}")
           for key, (md, tex) in TABLES.items()}
    md, tex = out["optimvariables"]
    out["optimvariables"] = (md + " Initial: the random particles; second worst underlined.",
                             tex + r" \emph{Initial}: the random particles; second worst underlined.")
    for table in tables:
        if not table.name.startswith("ladder_"):
            continue
        ladder = table.name[len("ladder_"):].removesuffix("_epe")
        if table.name.endswith("_epe"):
            md = (f"Severity ladder {ladder}: EPE against the ground truth ↓ on the clean frames and "
                  f"per rung, random (rand.) and adversarial (adv.) weather; RCE the relative "
                  f"corruption error, mean EPE increase over the rungs, on {name}; worst bold.")
            tex = (f"Severity ladder {latex_text(ladder)}: EPE against the ground truth "
                   r"$\downarrow$ on the clean frames and per rung, random (rand.) and adversarial "
                   f"(adv.) weather; RCE the relative corruption error, mean EPE increase over "
                   f"the rungs, on {latex_text(name)}; worst bold.")
        else:
            md = (f"Severity ladder {ladder}: robustness AEE(f, f̌) ↓ per rung, random (rand.) and "
                  f"adversarial (adv.) weather; R the robustness score, mean over the rungs, on "
                  f"{name}; worst bold.")
            tex = (f"Severity ladder {latex_text(ladder)}: robustness AEE$(f,\\check{{f}})$ "
                   r"$\downarrow$ per rung, random (rand.) and adversarial (adv.) weather; $R$ the "
                   f"robustness score, mean over the rungs, on {latex_text(name)}; worst bold.")
        out[table.name] = (md + mode, tex + mode_tex)
    return out


def _table_csv(rows: list[dict], columns: Sequence[str]) -> bytes:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(columns), lineterminator="\n")
    writer.writeheader()
    for r in rows:
        writer.writerow({k: ("" if r[k] is None else r[k]) for k in columns})
    return buf.getvalue().encode()


def _latex_document(tables: Sequence[Table], tex: dict) -> str:
    """The tables in one document; a table of the paper keeps its number there."""
    parts = []
    for t in tables:
        counter = "" if t.number is None else "\\setcounter{table}{" + str(t.number - 1) + "}\n"
        parts.append(counter + tex[t.name])
    return LATEX_PREAMBLE + "\n".join(parts) + "\n\\end{document}\n"


def write_tables(spec: BenchmarkSpec) -> dict[str, Path]:
    """Collect every cell's figures and write results.csv/json, the tables (Markdown, LaTeX, one
    file per table and all together) and the plot; with ladders also their curves
    (``ladders.csv``), scores (``robustness.csv``) and plot (``ladder.png``); return the paths."""
    rows = collect_results(spec)
    networks = list(spec.networks)
    out = Path(spec.out)
    curves = ladder_curves(rows, spec.ladders, table_networks(networks)) if spec.ladders else []
    document = {"weathergen_version": __version__, "input": spec.dataset.describe(),
                "seed": spec.seed,
                "networks": [checkpoint_record(spec, n) for n in networks],
                "settings": {"weather_steps": spec.steps, "lp_steps": spec.lp_steps,
                             "iters": spec.iters, "overrides": dict(spec.overrides),
                             "compat": spec.compat, "amp": spec.amp,
                             "ladders": list(spec.ladders)},
                "rows": rows}
    if curves:
        document["ladders"] = {"curves": _with_settings(curve_rows(curves), rows),
                               "scores": _with_settings(score_rows(curves), rows)}
    tables = build_tables(rows, networks, presets=spec.presets) + ladder_tables(curves, networks)
    # The settings behind the finished cells, one line each that differs: every caption's.
    settings = dict.fromkeys(f"{r['kind']} cells: {settings_text(r['settings'])}"
                             for r in rows if r.get("settings"))
    caption = {name: (md + "".join(f" Settings, {line}." for line in settings),
                      tex + "".join(f" Settings, {latex_text(line)}." for line in settings))
               for name, (md, tex) in captions(spec, tables).items()}
    md = {t.name: markdown_table(t, caption[t.name][0]) for t in tables}
    tex = {t.name: latex_table(t, caption[t.name][1]) for t in tables}
    paths = {"csv": out / "results.csv", "json": out / "results.json",
             "markdown": out / "tables.md", "latex": out / "tables.tex", "plot": out / "aee.png"}
    atomic_write_bytes(paths["csv"], _table_csv(rows, COLUMNS))
    atomic_write_bytes(paths["json"], (json.dumps(document, indent=2, sort_keys=True) + "\n").encode())
    for t in tables:
        atomic_write_bytes(out / "tables" / f"{t.name}.md", md[t.name].encode())
        atomic_write_bytes(out / "tables" / f"{t.name}.tex", tex[t.name].encode())
    atomic_write_bytes(paths["markdown"], "\n".join(md.values()).encode())
    atomic_write_bytes(paths["latex"], _latex_document(tables, tex).encode())
    draw_aee(paths["plot"], rows, table_networks(networks),
             [p for p in spec.presets if label_config(p) is None])
    if curves:
        paths.update(curves=out / "ladders.csv", scores=out / "robustness.csv",
                     ladder_plot=out / "ladder.png")
        atomic_write_bytes(paths["curves"], _table_csv(document["ladders"]["curves"],
                                                       CURVE_COLUMNS + SETTINGS_COLUMNS))
        atomic_write_bytes(paths["scores"], _table_csv(document["ladders"]["scores"],
                                                       SCORE_COLUMNS + SETTINGS_COLUMNS))
        draw_ladder(paths["ladder_plot"], curves, table_networks(networks))
    return paths
