"""`weathergen benchmark` on the demo scene with RAFT-small and tiny settings: the tables hold
exactly the per-run summaries, shards split the grid, and a rerun resumes."""

from __future__ import annotations

import csv
import json

import pytest
from click.testing import CliRunner

pytestmark = pytest.mark.slow


def invoke(args):
    from weathergen.cli.main import cli

    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


def grid_args(weights, out, *extra):
    return ["benchmark", "--networks", "raft-small", "--checkpoint", f"raft-small={weights}",
            "--presets", "snow,grey-color", "--lp", "ifgsm", "--steps", "1", "--lp-steps", "1",
            "--iters", "2", "--set", "count=100", "--scenes", "courtyard", "--frames-per-scene",
            "1", "--out", out, *extra]


@pytest.fixture(scope="module")
def bench(tmp_path_factory, raft_small_weights):
    out = tmp_path_factory.mktemp("bench") / "b"
    # two shards: each runs its own cells; together they finish the grid
    first = invoke(grid_args(raft_small_weights, out, "--shard", "1/2", "--quiet"))
    assert first.exit_code == 0, first.output
    done = sorted(p.parent.name for p in (out / "runs").glob("*/*/summary.json"))
    assert done == ["ifgsm", "snow"]                  # cells 1 and 3 of snow, grey-color, ifgsm
    partial = json.loads((out / "results.json").read_text())
    assert [r["aee_adversarial"] is None for r in partial["rows"]] == [False, True, False]
    partial_md = (out / "tables.md").read_text()
    assert "| δc (grey-color) | – |" in partial_md and "| Initial | – |" in partial_md
    assert r"$\delta_{c}$ (grey-color) & -- \\" in (out / "tables.tex").read_text()
    second = invoke(grid_args(raft_small_weights, out, "--shard", "2/2"))
    assert second.exit_code == 0, second.output
    return out, second.output


def summary(out, label):
    return json.loads((out / "runs" / "raft-small" / label / "summary.json").read_text())


def test_tables_equal_the_per_run_summaries(bench, raft_small_weights):
    out, output = bench
    snow, grey, ifgsm = (summary(out, x) for x in ("snow", "grey-color", "ifgsm"))
    doc = json.loads((out / "results.json").read_text())
    rows = {r["label"]: r for r in doc["rows"]}
    for label, s in (("snow", snow), ("grey-color", grey), ("ifgsm", ifgsm)):
        for key in ("aee_random", "aee_adversarial", "target_initial", "target_adversarial",
                    "aee_weather_px", "aee_clear_px", "fl_all", "outliers_3px", "compat", "amp"):
            assert rows[label][key] == s[key], (label, key)
        assert rows[label]["pairs"] == 1
    assert rows["snow"]["fl_all"] is not None and rows["snow"]["compat"] == "paper"
    assert doc["settings"]["compat"] == "paper"
    # mixed precision as each run resolved it (off on the CPU), and as it was asked for
    assert rows["snow"]["amp"] is False and rows["ifgsm"]["amp"] is False
    assert doc["settings"]["amp"] is None
    with open(out / "results.csv", newline="") as fh:
        csv_rows = {r["label"]: r for r in csv.DictReader(fh)}
    assert float(csv_rows["ifgsm"]["aee_adversarial"]) == pytest.approx(ifgsm["aee_adversarial"])
    assert float(csv_rows["snow"]["aee_weather_px"]) == pytest.approx(snow["aee_weather_px"])
    assert csv_rows["snow"]["amp"] == "False"
    # network and checkpoint recorded
    (net,) = doc["networks"]
    assert net["network"] == "raft-small" and net["checkpoint"] == str(raft_small_weights)
    assert len(net["sha256"]) == 64
    md = (out / "tables.md").read_text()
    tex = (out / "tables.tex").read_text()
    f = lambda v: f"{v:.2f}"                                        # noqa: E731
    # Table 5: the Lp baseline beside the adversarial snow, the worst bold.
    worst = max(ifgsm["aee_adversarial"], snow["aee_adversarial"])
    for name, value in (("I-FGSM", ifgsm["aee_adversarial"]),
                        ("Snow (ours)", snow["aee_adversarial"])):
        shown = f"**{f(value)}**" if value == worst else f(value)
        assert f"| {name} | {shown} |" in md
        shown = r"\textbf{" + f(value) + "}" if value == worst else f(value)
        assert f"{name} & {shown} \\\\" in tex
    # Table 2: the random weather of each preset; snow is the paper's Particles row 3000.
    augmentations = (out / "tables" / "augmentations.md").read_text()
    assert f"| **Particles** |  |\n| 3000 (snow) | **{f(snow['aee_random'])}** |" in augmentations
    # Table 3: Initial (not ranked) above the configuration's adversarial figure.
    assert f"| Initial | {f(grey['aee_random'])} |" in md
    assert f"| δc (grey-color) | **{f(grey['aee_adversarial'])}** |" in md
    # Table 4: the adversarial weather alone (its random figure is Table 2's).
    weather = (out / "tables" / "weatherattacks.md").read_text()
    assert f"| snow | **{f(snow['aee_adversarial'])}** |" in weather
    assert "| Attack | raft-small |" in weather and "rand." not in weather
    # numbered as in the paper, in its order
    assert [line.split(":")[0] for line in md.splitlines() if line.startswith("### ")] == [
        "### Table 2 (augmentations)", "### Table 3 (optimvariables)",
        "### Table 4 (weatherattacks)", "### Table 5 (of_attacks)"]
    for number, label in ((2, "augmentations"), (3, "optimvariables"), (4, "weatherattacks"),
                          (5, "of_attacks")):
        at = tex.index("\\setcounter{table}{" + str(number - 1) + "}")
        assert tex.index("\\begin{table}", at) < tex.index("\\label{table:" + label + "}", at)
    for label in ("augmentations", "optimvariables", "weatherattacks", "of_attacks"):
        assert r"\label{table:" + label + "}" in tex
        assert (out / "tables" / f"{label}.md").read_text() in md
        assert (out / "tables" / f"{label}.tex").read_text() in tex
    assert "of_attacks" in output and "aee.png" in output


def tabulars(tex: str) -> list[tuple[str, list[str]]]:
    """Every tabular of a LaTeX text: its column spec and its rows (lines ending in \\)."""
    out = []
    for block in tex.split(r"\begin{tabular}{")[1:]:
        spec, body = block.split("}", 1)
        body = body.split(r"\end{tabular}")[0]
        rows = [line for line in body.splitlines() if line.rstrip().endswith("\\\\")]
        out.append((spec, rows))
    return out


def cell_count(row: str) -> int:
    r"""Columns a LaTeX row fills: its cells, a \multicolumn{n} counting n."""
    import re

    count = 0
    for cell in row.rstrip().removesuffix("\\\\").split(" & "):
        m = re.match(r"\\multicolumn\{(\d+)\}", cell.strip())
        count += int(m.group(1)) if m else 1
    return count


def test_table_layout_column_counts_and_a_whole_document(bench):
    """Every row of every table fills every column (Markdown and LaTeX); tables.tex is a whole
    document (preamble, the tables, end)."""
    out, _ = bench
    tex = (out / "tables.tex").read_text()
    assert tex.startswith("\\documentclass{article}") and tex.rstrip().endswith("\\end{document}")
    for package in ("booktabs", "graphicx"):
        assert "\\usepackage{" + package + "}" in tex
    found = tabulars(tex)
    assert len(found) == 4
    widths = []
    for spec, rows in found:
        assert rows
        for row in rows:
            assert cell_count(row) == len(spec), (spec, row)
        widths.append(len(spec))
    assert widths == [2, 2, 2, 2]             # one network, one column each
    for block in (out / "tables.md").read_text().split("### ")[1:]:
        lines = [ln for ln in block.splitlines() if ln.startswith("|")]
        bars = {ln.replace(r"\|", "").count("|") for ln in lines}
        assert len(bars) == 1, block                               # every row as wide as the head
        assert all("|  |" not in ln for ln in lines if not ln.startswith("| **"))  # no empty cell


def test_plot_of_aee_per_network_and_preset(bench):
    from weathergen.benchmark.plot import PALETTE
    from weathergen.io.images import read_image

    out, _ = bench
    img = read_image(out / "aee.png")
    assert img.ndim == 3 and img.shape[2] == 3 and img.shape[0] > 300
    # The network's two bars: light (random) and dark (adversarial) in its colour.
    pixels = {tuple(int(round(c * 255)) for c in px) for px in img.reshape(-1, 3)[::7]}
    assert PALETTE[0] in pixels
    assert any(p != PALETTE[0] and p[2] > p[0] and p not in ((255, 255, 255),) for p in pixels)


def test_latex_escapes_and_markdown_pipes():
    from weathergen.benchmark import build_tables, latex_table, markdown_table

    rows = [{"network": "net_x&y", "kind": "weather", "label": "my_preset%#|", "aee_random": 1.0,
             "aee_adversarial": 2.0},
            {"network": "net_x&y", "kind": "weather", "label": "alpha-blue", "aee_random": 3.0,
             "aee_adversarial": None}]
    tables = {t.name: t for t in build_tables(rows, ["net_x&y"])}
    assert sorted(tables) == ["augmentations", "weatherattacks"]   # no configuration, no Lp
    tex = latex_table(tables["augmentations"], "c")
    assert r"my\_preset\%\#|" in tex and r"net\_x\&y" in tex
    assert r"\emph{Color $\alpha$-blending}" in tex            # the paper's family heading
    assert "α" not in tex and "my_preset" not in tex
    md = markdown_table(tables["weatherattacks"], "c")
    assert r"| my_preset%#\| | **2.00** |" in md
    assert "| alpha-blue | – |" in md


def test_augmentations_are_the_papers_families_each_with_its_worst_bold():
    """Table 2 as the paper lays it out: families in the paper's order under their headings, their
    rows in the paper's order whatever the order asked for, the main augmentations in their
    families' rows, presets outside the families after them, the worst of each family bold (rows
    alone in their family are ranked with one another)."""
    from weathergen.benchmark import build_tables, latex_table, markdown_table

    figures = {"fog": 1.0, "snow": 2.0, "rain": 3.0, "sparks": 4.0, "particles-1000": 1.5,
               "particles-5000": 7.0, "motion-blur-0.0375": 2.5, "own-preset": 0.5}
    rows = [{"network": "a", "kind": "weather", "label": label, "aee_random": v,
             "aee_adversarial": None} for label, v in figures.items()]
    (table,) = [t for t in build_tables(rows, ["a"]) if t.name == "augmentations"]
    md = markdown_table(table, "c").split("\n")
    body = [line for line in md[md.index("| --- | ---: |") + 1:] if line]
    assert body == ["| **Particles** |  |", "| 1000 | 1.50 |", "| 3000 (snow) | 2.00 |",
                    "| 5000 | **7.00** |",
                    "| **Motion blur** |  |", "| 0.0375 | 2.50 |", "| 0.15 (rain) | **3.00** |",
                    "| **Color additive** |  |", "| red (sparks) | **4.00** |",
                    "| **Size** |  |", "| fog | 1.00 |", "| own-preset | 0.50 |"]
    tex = latex_table(table, "c")
    assert "\\emph{Particles}} \\\\\n1000 & 1.50 \\\\\n3000 (snow) & 2.00" in tex
    from weathergen.engine import load_preset

    for main, member in (("snow", "particles-3000"), ("rain", "motion-blur-0.15"),
                         ("sparks", "additive-red"), ("fog", "size-fog")):
        a, b = load_preset(main).to_dict(), load_preset(member).to_dict()
        assert {k for k in a if a[k] != b[k]} <= {"name", "source", "description"}, main


def test_optimvariables_marks_the_worst_bold_and_the_second_worst_underlined():
    """Table 3 as the paper marks it, per column: the worst configuration bold, the second worst
    underlined; the Initial row (random particles) takes part in neither, however large."""
    from weathergen.benchmark import build_tables, latex_table, markdown_table

    figures = {"grey-offset1": (9.0, 5.0, 7.0), "grey-offset2": (9.0, 6.0, 6.0),
               "grey-color": (9.0, 4.0, 8.0)}      # (random, adversarial net a, net b)
    rows = [{"network": net, "kind": "weather", "label": label, "aee_random": v[0],
             "aee_adversarial": v[1 + i]}
            for i, net in enumerate(("a", "b")) for label, v in figures.items()]
    (table,) = [t for t in build_tables(rows, ["a", "b"]) if t.name == "optimvariables"]
    md = markdown_table(table, "c")
    assert "| Initial | 9.00 | 9.00 |" in md
    assert "| δ1 (grey-offset1) | <u>5.00</u> | <u>7.00</u> |" in md
    assert "| δ2 (grey-offset2) | **6.00** | 6.00 |" in md
    assert "| δc (grey-color) | 4.00 | **8.00** |" in md
    tex = latex_table(table, "c")
    assert r"$\delta_{2}$ (grey-offset2) & \textbf{6.00} & 6.00 \\" in tex
    assert r"$\delta_{1}$ (grey-offset1) & \underline{5.00} & \underline{7.00} \\" in tex


def test_rerun_resumes_without_redoing(bench, raft_small_weights):
    out, _ = bench
    before = {p: p.stat().st_mtime_ns for p in (out / "runs").rglob("*.png")}
    again = invoke(grid_args(raft_small_weights, out, "--quiet"))
    assert again.exit_code == 0, again.output
    assert {p: p.stat().st_mtime_ns for p in (out / "runs").rglob("*.png")} == before


def test_a_finished_benchmark_leaves_no_lock_file(bench):
    out, _ = bench
    runs = list((out / "runs").glob("*/*/manifest.json"))
    assert len(runs) == len(json.loads((out / "results.json").read_text())["rows"])   # every cell ran
    assert not list(out.rglob(".weathergen-lock*"))


def test_bad_options_fail_before_writing(tmp_path):
    out = tmp_path / "b"
    result = invoke(["benchmark", "--presets", "hail", "--lp", "", "--out", out])
    assert result.exit_code == 2 and "hail" in result.output
    assert not out.exists()
    result = invoke(["benchmark", "--lp", "fgsm", "--presets", "", "--out", out])
    assert result.exit_code == 2 and "fgsm" in result.output
    # the benchmark's own options are named, not the attack's (--method, --preset)
    assert result.output.strip() == "Error: --lp 'fgsm': expected pcfa, ifgsm"
    result = invoke(["benchmark", "--checkpoint", "raft", "--out", out])
    assert result.exit_code == 2 and "NETWORK=FILE_OR_NAME" in result.output
    result = invoke(["benchmark", "--networks", "raft-small", "--amp", "--out", out])
    assert result.exit_code == 2 and "--amp needs a CUDA device" in result.output
    result = invoke(["benchmark", "--networks", "raft-small,raft,raft-small", "--out", out])
    assert result.output.strip() == "Error: --networks names 'raft-small' twice"
    result = invoke(["benchmark", "--networks", "raft-small", "--checkpoint", "raft=raft-things",
                     "--out", out])
    assert result.output.strip() == ("Error: --checkpoint raft=raft-things: 'raft' is not among "
                                     "--networks (raft-small)")
    result = invoke(["benchmark", "--networks", "raft-small,nets.py:build", "--out", out])
    assert result.output.strip() == ("Error: --networks 'nets.py:build': the file 'nets.py' does "
                                     "not exist")
    assert not out.exists()


@pytest.mark.parametrize("amp, expected", [(None, {"gma": True, "raft": False}),
                                           (False, {"gma": False, "raft": False})])
def test_amp_is_passed_on_to_every_run(demo_root, tmp_path, amp, expected):
    """Each run gets the request (default: each network's paper setting on CUDA) and records the
    resolved value in its manifest; nothing runs here, so no CUDA device is needed."""
    from weathergen.benchmark import BenchmarkSpec, run_grid
    from weathergen.datasets import open_dataset

    spec = BenchmarkSpec(dataset=open_dataset("demo", frames_per_scene=1), out=tmp_path,
                         networks=["gma", "raft"], presets=["snow"], lp_methods=["pcfa"],
                         device="cuda", amp=amp)
    jobs = []
    run_grid(spec, execute=jobs.append)
    assert [(j.model.name, j.amp) for j in jobs] == [(n, amp) for n in ("gma", "gma", "raft", "raft")]
    assert {j.model.name: j.config()["model"]["amp"] for j in jobs} == expected


def test_amp_for_a_network_without_the_mode_fails_before_any_run(demo_root, tmp_path):
    from weathergen.benchmark import BenchmarkSpec, run_grid
    from weathergen.datasets import open_dataset
    from weathergen.errors import ConfigError

    spec = BenchmarkSpec(dataset=open_dataset("demo", frames_per_scene=1), out=tmp_path,
                         networks=["gma", "spynet"], presets=["snow"], lp_methods=[],
                         device="cuda", amp=True)
    jobs = []
    with pytest.raises(ConfigError, match="'spynet' has no mixed-precision mode"):
        run_grid(spec, execute=jobs.append)
    assert jobs == []


def test_default_selection_is_five_pairs_per_scene(demo_root):
    from weathergen.benchmark import tr115_default
    from weathergen.datasets import open_dataset

    everything = open_dataset("demo")
    assert tr115_default(everything).selection.frames_per_scene == 5
    chosen = open_dataset("demo", frames_per_scene=1)
    assert tr115_default(chosen) is chosen


def test_compat_reaches_every_weather_run(demo_root):
    """--compat is passed to each weather cell's attack settings (Lp cells have none)."""
    from weathergen.benchmark import BenchmarkSpec, cell_job
    from weathergen.datasets import open_dataset

    for compat in ("paper", "reference"):
        spec = BenchmarkSpec(dataset=open_dataset("demo", frames_per_scene=1), out="b",
                             networks=["raft-small"], presets=["snow", "fog"],
                             lp_methods=["pcfa"], compat=compat)
        jobs = {c.label: cell_job(spec, c) for c in spec.cells()}
        assert jobs["snow"].settings.compat == jobs["fog"].settings.compat == compat
        assert jobs["snow"].config()["attack"]["compat"] == compat
        assert jobs["pcfa"].settings is None


def test_a_combined_preset_is_one_weather_cell(tmp_path, raft_small_weights):
    """`--presets snow-light+fog-light`: one attack run of the combination, its row in the
    results the run's own summary, its label in the tables."""
    out = tmp_path / "b"
    result = invoke(["benchmark", "--networks", "raft-small", "--checkpoint",
                     f"raft-small={raft_small_weights}", "--presets", "snow-light+fog-light",
                     "--lp", "", "--steps", "1", "--iters", "2", "--scenes", "courtyard",
                     "--frames-per-scene", "1", "--out", out, "--quiet"])
    assert result.exit_code == 0, result.output
    run = summary(out, "snow-light+fog-light")
    row, = json.loads((out / "results.json").read_text())["rows"]
    assert row["label"] == "snow-light+fog-light" and row["kind"] == "weather"
    assert row["aee_adversarial"] == run["aee_adversarial"] and run["pairs"] == 1
    manifest = json.loads((out / "runs" / "raft-small" / "snow-light+fog-light"
                           / "manifest.json").read_text())
    assert manifest["preset_name"] == "snow-light+fog-light"
    assert "| snow-light+fog-light |" in (out / "tables.md").read_text()
