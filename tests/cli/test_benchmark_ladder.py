"""Severity ladders (`benchmark --ladder`): the curves and scores from the runs' summaries, their
tables and plot, on the demo scene with a network of a few convolutions; and the paper's tables
in the paper's order whatever the order asked for (networks, rows)."""

from __future__ import annotations

import csv
import json
import textwrap

import pytest
from click.testing import CliRunner

CONVS = textwrap.dedent('''
    import torch
    from torch import nn

    class Convs(nn.Module):
        def __init__(self, width, gain):
            super().__init__()
            self.gain = gain
            self.body = nn.Sequential(nn.Conv2d(6, width, 3, padding=1), nn.ReLU(),
                                      nn.Conv2d(width, 2, 3, padding=1))

        def forward(self, image1, image2):
            return self.gain * self.body(torch.cat([image1, image2], 1))

    def build():
        torch.manual_seed(0)
        return Convs(8, 4.0)

    def wide():
        torch.manual_seed(1)
        return Convs(16, 6.0)
''')


def invoke(args):
    from weathergen.cli.main import cli

    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


# -- the paper's tables: numbered, ordered, laid out as the paper's ------------------------------

def rows_for(networks, labels, lp=()):
    """Result rows with distinct figures (random = i + j/10, adversarial twice that)."""
    rows = []
    for i, net in enumerate(networks):
        for j, label in enumerate(labels):
            rows.append({"network": net, "kind": "weather", "label": label,
                         "aee_random": i + j / 10, "aee_adversarial": 2 * (i + j / 10)})
        for j, method in enumerate(lp):
            rows.append({"network": net, "kind": "lp", "label": method, "aee_random": None,
                         "aee_adversarial": 10 + i + j})
    return rows


def body(markdown: str) -> list[str]:
    """The first cell of every row below a Markdown table's rule."""
    lines = markdown.split("\n")
    rule = next(i for i, x in enumerate(lines) if x.startswith("| ---"))
    return [line.split(" |")[0][2:] for line in lines[rule + 1:] if line.startswith("| ")]


def test_networks_and_rows_come_in_the_papers_order_whatever_the_order_asked():
    from weathergen.benchmark import build_tables, markdown_table

    networks = ["mine.py:net", "flowformer", "raft", "other", "flownet2", "spynet", "gma",
                "flownetcrobust"]
    labels = ["fog", "particles-5000", "own", "snow", "grey-all", "sparks", "grey-color",
              "grey-offsets", "rain", "grey-offset1", "motion-blur-0.0", "grey-appearance",
              "particles-1000", "size-small", "additive-blue", "additive-white"]
    tables = build_tables(rows_for(networks, labels, lp=["ifgsm", "pcfa"]), networks)
    assert [(t.number, t.name) for t in tables] == [(2, "augmentations"), (3, "optimvariables"),
                                                    (4, "weatherattacks"), (5, "of_attacks")]
    names = ["FN2", "FNCR", "SpyNet", "RAFT", "GMA", "FF", "mine.net", "other"]
    for t in tables:
        assert t.columns == names, t.name           # the paper's six, then the others as given
    md = {t.name: markdown_table(t, "c") for t in tables}
    assert body(md["augmentations"]) == [
        "**Particles**", "1000", "3000 (snow)", "5000", "**Motion blur**", "0.0", "0.15 (rain)",
        "**Color additive**", "white", "red (sparks)", "blue", "**Size**", "small", "fog", "own"]
    assert body(md["optimvariables"]) == ["Initial", "δ1 (grey-offset1)", "δc (grey-color)",
                                          "δ1,2 (grey-offsets)", "δc,θ (grey-appearance)",
                                          "δall (grey-all)"]
    assert [s for s, _ in tables[1].sections] == [None] * 4          # Initial, 1, 2, all: midrules
    assert body(md["weatherattacks"]) == ["snow", "rain", "sparks", "fog", "particles-5000", "own",
                                          "motion-blur-0.0", "particles-1000", "size-small",
                                          "additive-blue", "additive-white"]
    assert body(md["of_attacks"]) == ["PCFA", "I-FGSM", "Snow (ours)"]
    # the weather-attack table is adversarial only: FN2's (network 4) adversarial snow is 2 * 4.3
    assert md["weatherattacks"].split("\n")[4].startswith("| snow | 8.60 |")
    assert "### Table 4 (weatherattacks)" in md["weatherattacks"]


def test_a_ladder_names_three_rungs_and_scores_only_whole_curves():
    from weathergen.benchmark import (Curve, available_ladders, ladder_curves, ladder_presets,
                                      score_rows)
    from weathergen.errors import ConfigError

    assert {"snow", "rain", "fog"} <= set(available_ladders())
    assert ladder_presets("snow") == ["snow-light", "snow-moderate", "snow-heavy"]
    with pytest.raises(ConfigError, match="no such severity ladder; ladders: .*snow"):
        ladder_presets("hail")
    rows = [{"network": "n", "kind": "weather", "label": f"fog-{r}", "epe_benign": 2.0,
             "aee_random": a, "epe_random": e, "aee_adversarial": 2 * a, "epe_adversarial": 2 * e}
            for r, a, e in (("light", 1.0, 3.0), ("moderate", 2.0, 4.0), ("heavy", 6.0, 5.0))]
    random, adversarial = ladder_curves(rows, ["fog"], ["n"])
    assert random.points == [("clean", 0.0, 2.0), ("fog-light", 1.0, 3.0),
                             ("fog-moderate", 2.0, 4.0), ("fog-heavy", 6.0, 5.0)]
    assert random.robustness() == pytest.approx(3.0)             # (1 + 2 + 6) / 3
    assert random.relative_error() == pytest.approx(2.0)         # (1 + 2 + 3) / 3
    assert adversarial.robustness() == pytest.approx(6.0)
    assert adversarial.relative_error() == pytest.approx((4 + 6 + 8) / 3)
    unfinished = Curve("fog", "n", "random", [("clean", 0.0, 2.0), ("fog-light", 1.0, 3.0),
                                              ("fog-moderate", None, None)])
    (row,) = score_rows([unfinished])
    assert row["robustness"] is None and row["relative_error"] is None and row["rungs_done"] == 1
    # no ground truth: a robustness score, no relative error
    blind = Curve("fog", "n", "random", [("clean", 0.0, None), ("fog-light", 1.0, None)])
    assert blind.robustness() == 1.0 and blind.relative_error() is None


def test_a_bad_ladder_fails_before_writing(tmp_path):
    out = tmp_path / "b"
    result = invoke(["benchmark", "--ladder", "snow,hail", "--out", out])
    assert result.exit_code == 2 and result.output.startswith("Error: --ladder 'hail'")
    assert len(result.output.strip().splitlines()) == 1 and not out.exists()


# -- a ladder benchmark on the demo scene -------------------------------------------------------

@pytest.fixture(scope="module")
def ladder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("ladder")
    (folder / "convs.py").write_text(CONVS)
    out = folder / "b"
    # two networks of a few convolutions, one pair, one attack step, the field snow kept within
    # 1 m of the camera (fewer particles, the same ladder)
    result = invoke(["benchmark", "--networks", f"{folder / 'convs.py'}:build,{folder / 'convs.py'}:wide",
                     "--ladder", "snow", "--steps", "1", "--set", "far=1", "--scenes", "courtyard",
                     "--frames-per-scene", "1", "--out", out])
    assert result.exit_code == 0, result.output
    return out, result.output


@pytest.mark.slow
def test_the_ladder_runs_its_three_rungs_and_nothing_else(ladder):
    out, output = ladder
    runs = sorted(p.relative_to(out / "runs").parent.as_posix()
                  for p in (out / "runs").glob("*/*/summary.json"))
    assert runs == [f"{net}/snow-{rung}" for net in ("convs.build", "convs.wide")
                    for rung in ("heavy", "light", "moderate")]
    assert "ladders.csv" in output and "robustness.csv" in output
    doc = json.loads((out / "results.json").read_text())
    assert doc["settings"]["ladders"] == ["snow"]
    # the paper's tables need presets of their own: only the ladder's tables are written
    assert sorted(p.name for p in (out / "tables").glob("*.md")) == ["ladder_snow.md",
                                                                     "ladder_snow_epe.md"]


@pytest.mark.slow
def test_the_curves_and_scores_are_the_runs_figures(ladder):
    out, _ = ladder
    with open(out / "ladders.csv", newline="") as fh:
        curves = list(csv.DictReader(fh))
    with open(out / "robustness.csv", newline="") as fh:
        scores = {(r["network"].rsplit(":", 1)[1], r["mode"]): r for r in csv.DictReader(fh)}
    assert len(curves) == 2 * 2 * 4 and len(scores) == 4        # networks x modes x points
    for net in ("build", "wide"):
        summaries = [json.loads((out / "runs" / f"convs.{net}" / f"snow-{rung}" / "summary.json")
                                .read_text()) for rung in ("light", "moderate", "heavy")]
        for mode, aee, epe in (("random", "aee_random", "epe_random"),
                               ("adversarial", "aee_adversarial", "epe_adversarial")):
            points = [r for r in curves if r["network"].endswith(f":{net}") and r["mode"] == mode]
            assert [r["label"] for r in points] == ["clean", "snow-light", "snow-moderate",
                                                    "snow-heavy"]
            assert float(points[0]["aee"]) == 0.0
            assert float(points[0]["epe"]) == pytest.approx(summaries[0]["epe_benign"])
            for point, s in zip(points[1:], summaries):
                assert float(point["aee"]) == pytest.approx(s[aee])
                assert float(point["epe"]) == pytest.approx(s[epe])
            score = scores[(net, mode)]
            assert float(score["robustness"]) == pytest.approx(sum(s[aee] for s in summaries) / 3)
            assert float(score["relative_error"]) == pytest.approx(
                sum(s[epe] - s["epe_benign"] for s in summaries) / 3)
            assert score["rungs_done"] == "3" and float(score["epe_clean"]) > 0
        # heavier snow moves the flow further (random weather, the same seed)
        light, _, heavy = (s["aee_random"] for s in summaries)
        assert heavy > light > 0


@pytest.mark.slow
def test_the_ladder_tables_and_plot(ladder):
    from weathergen.benchmark.plot import PALETTE
    from weathergen.io.images import read_image

    out, _ = ladder
    md = (out / "tables" / "ladder_snow.md").read_text()
    assert "| Network | rand. light | rand. moderate | rand. heavy | rand. R | adv. light |" in md
    with open(out / "robustness.csv", newline="") as fh:
        score = next(r for r in csv.DictReader(fh) if r["network"].endswith(":build")
                     and r["mode"] == "adversarial")
    row = next(line for line in md.splitlines() if line.startswith("| convs.build"))
    assert f"{float(score['robustness']):.2f}" in row.split("|")[9]        # adv. R
    assert "clean EPE" in (out / "tables" / "ladder_snow_epe.md").read_text()
    tex = (out / "tables.tex").read_text()
    assert r"\multicolumn{4}{c}{adversarial}" in tex and "setcounter" not in tex
    img = read_image(out / "ladder.png")
    assert img.shape[0] > 250 and img.shape[1] > 600
    pixels = {tuple(int(round(c * 255)) for c in px) for px in img.reshape(-1, 3)}
    assert PALETTE[0] in pixels and PALETTE[1] in pixels        # one colour per network
