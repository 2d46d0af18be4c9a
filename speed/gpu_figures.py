"""The GPU figures page, docs/figures/gpu.md: every GPU figure, for reading, written from the JSON
files of ``make gpu-check`` (``gpu-check.json``) and of the GPU session (``speed/gpu_session.sh``:
``gpu-session.json``).

Both scripts rewrite the page beside their JSON file each time they write it
(:func:`write_page`); after copying a JSON file into docs/figures by hand, rewrite the page with::

    python speed/gpu_figures.py [FOLDER]        # default docs/figures

Each section names the machine (GPU, its memory, torch, CUDA) and the tree (git commit) its JSON
records. Nothing here measures: the page shows the JSON's figures and what follows from them by
arithmetic (milliseconds per pair-step = 1000 / pair-steps per second; GPU-hours = pair-steps /
pair-steps per second / 3600; shares and ratios).
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path
from typing import Callable, Optional

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_common  # noqa: E402  (atomic writes)

ROOT = Path(__file__).resolve().parents[1]
FOLDER = ROOT / "docs" / "figures"
PAGE, CHECK, SESSION = "gpu.md", "gpu-check.json", "gpu-session.json"
DASH = "–"


# -- the page ---------------------------------------------------------------------------------------

def page(check: Optional[dict], session: Optional[dict]) -> str:
    """The Markdown page of a ``make gpu-check`` JSON and a GPU session's JSON (either None)."""
    lines = ["# GPU figures", "",
             f"Written from [{CHECK}]({CHECK}) (`make gpu-check`) and [{SESSION}]({SESSION}) "
             "(`speed/gpu_session.sh`) by `speed/gpu_figures.py`, each time either writes its "
             "JSON; do not edit by hand. Each section names the GPU, torch and tree it was "
             "measured on. CPU figures: [bench.md](bench.md) (`make bench`).", ""]
    lines += session_section(session) if session is not None else \
        ["## GPU session", "", f"No {SESSION} yet.", ""]
    lines += check_section(check) if check is not None else \
        ["## make gpu-check", "", f"No {CHECK} yet.", ""]
    return "\n".join(lines)


def write_page(path: Path, check: Optional[Path], session: Optional[Path]) -> Path:
    """Write the page to ``path`` from the JSON files ``check`` and ``session`` (a file that is
    None or missing: that section says so)."""
    def load(p: Optional[Path]) -> Optional[dict]:
        return json.loads(Path(p).read_text()) if p is not None and Path(p).exists() else None

    bench_common.write_atomic(path, page(load(check), load(session)))
    return Path(path)


def write_folder(folder: Path = FOLDER) -> Path:
    """Rewrite ``folder/gpu.md`` from ``folder``'s gpu-check.json and gpu-session.json."""
    folder = Path(folder)
    return write_page(folder / PAGE, folder / CHECK, folder / SESSION)


# -- shared pieces ----------------------------------------------------------------------------------

def table(head: list[str], rows: list[list[str]], right: Optional[list[bool]] = None) -> list[str]:
    """A Markdown table; ``right[i]``: column i aligned right (default: all but the first)."""
    right = right or [i > 0 for i in range(len(head))]
    rule = "|" + "|".join("---:" if r else "---" for r in right) + "|"
    return ["| " + " | ".join(head) + " |", rule] + ["| " + " | ".join(r) + " |" for r in rows] + [""]


def num(value: Optional[float], digits: int = 2, suffix: str = "") -> str:
    """``value`` with ``digits`` decimals (a dash for None)."""
    return DASH if value is None else f"{value:.{digits}f}{suffix}"


def percent(value: Optional[float]) -> str:
    return DASH if value is None else f"{value * 100:.0f} %"


def machine_line(m: dict) -> str:
    """``- machine: GPU (memory), CUDA, torch, Python, CPUs, host`` from a JSON's ``machine``."""
    parts = [m.get("gpu") or "no GPU"]
    if m.get("gpu_memory_gib"):
        parts[0] += f" ({m['gpu_memory_gib']:.1f} GiB)"
    parts += [f"CUDA {m['cuda']}" if m.get("cuda") else "", f"torch {m.get('torch')}",
              f"Python {m['python']}" if m.get("python") else "",
              f"{m['cpus']} CPUs" if m.get("cpus") else "", f"host {m['host']}" if m.get("host") else ""]
    return "- machine: " + ", ".join(p for p in parts if p)


def tree_line(tree: Optional[dict]) -> str:
    """``- tree: `COMMIT`[ with uncommitted changes]`` from a JSON's ``tree``."""
    if not tree or not tree.get("commit"):
        return "- tree: not recorded in this JSON file"
    return f"- tree: `{tree['commit'][:12]}`" + (" with uncommitted changes" if tree.get("dirty") else "")


def not_run(section: dict) -> Optional[str]:
    """The line of a section that was skipped or failed, else None."""
    if "skipped" in section:
        return f"Skipped ({section['skipped']})."
    if "failed" in section:
        return f"Failed: {section['failed']}"
    return None


# -- the GPU session --------------------------------------------------------------------------------

def session_section(data: dict) -> list[str]:
    """The GPU session's section: machine and tree, then each of its sections."""
    sections = data.get("sections", {})
    lines = ["## GPU session", "", "`speed/gpu_session.sh` (`speed/gpu_session.py`)", "",
             machine_line(data.get("machine", {})), tree_line(data.get("tree"))]
    if data.get("elapsed_s") is not None:
        lines.append(f"- run: {data['elapsed_s']:.0f} s in all")
    if data.get("quick"):
        lines.append("- quick: tiny sizes, a smoke test; the figures mean nothing")
    lines.append("")
    parts: list[tuple[str, str, Callable[[dict, dict], list[str]]]] = [
        ("tests", "CUDA tests of device-side sampling", tests_part),
        ("tables", "Attack throughput per network", throughput_part),
        ("tables", "GPU-hours of the paper's Tables 2-5", hours_part),
        ("options", "Speed options", options_part),
        ("sampler", "Sampling on the device", sampler_part),
        ("training", "A training batch's weather against a RAFT training step", training_part)]
    for key, title, part in parts:
        if key not in sections:
            continue
        section = sections[key]
        lines += [f"### {title}", ""]
        stopped = not_run(section)
        lines += [stopped, ""] if stopped else part(section, sections)
    return lines


def tests_part(section: dict, _sections: dict) -> list[str]:
    tail = [line for line in section.get("tail", []) if line.strip()]
    last = tail[-1] if tail else "no output"
    return [f"`pytest -m cuda -k \"sampling_on or fields_views\"`: exit status "
            f"{section.get('returncode')}, {last}", ""]


def throughput_part(section: dict, _sections: dict) -> list[str]:
    """Per network and precision: the best batch, its pair-steps/s and ms, the network's share."""
    head = ["network", "precision", "options", "best batch", "pair-steps/s", "ms per pair-step",
            "network alone, share of a step", "forward pairs/s", "GPU memory at best batch (GiB)",
            "batches tried: pair-steps/s", "stop"]
    rows = []
    for r in section.get("measured", []):
        best = r.get("batches", {}).get(str(r.get("best_batch")), {})
        tried = ", ".join(f"{b}: {v['pair_steps_per_second']:.2f}" for b, v in r.get("batches", {}).items())
        rows.append([r["network"], r["precision"], r.get("options", "-"), str(r.get("best_batch") or DASH),
                     num(r.get("attack")), num(1000 / r["attack"] if r.get("attack") else None, 1),
                     percent(r.get("network_share")), num(r.get("forward")), num(best.get("memory_gib"), 1),
                     tried or DASH, r.get("stop", "")])
    right = [False, False, False] + [True] * 6 + [False, False]
    return ["Each network's attack (render, network, loss, backward, Adam update) at growing batch "
            "sizes; the best batch's figures.", ""] + table(head, rows, right)


def table4_pair_steps(section: dict) -> Optional[int]:
    """Pair-steps of Table 4 per network: the JSON's ``counts`` where it has them, else what its
    allowance implies (target hours x 3600 / allowed seconds per pair-step)."""
    counts = section.get("counts", {}).get("4", {}).get("pair_steps")
    if counts:
        return int(counts)
    for fig in section.get("hours", {}).values():
        if fig.get("table4_ms_per_pair_step_allowed"):
            return round(fig["target_hours_table4"] * 3600 * 1000 / fig["table4_ms_per_pair_step_allowed"])
    return None


def hours_part(section: dict, _sections: dict) -> list[str]:
    """Per precision: GPU-hours per network and table, and what the Table 4 target allows."""
    lines = []
    steps4 = table4_pair_steps(section)
    for precision, fig in section.get("hours", {}).items():
        hours, tps = fig["hours"], fig["throughput"]
        tables = [t for t in hours["all"] if t != "total"]
        head = ["network", "pair-steps/s (source)"] + [f"Table {t}" for t in tables] + \
            ["total", "share of the total"]
        rows = []
        for name, h in hours.items():
            rate = "" if name == "all" else f"{tps[name]['attack']:.2f} ({tps[name].get('source', '')})"
            rows.append([f"**all {len(tps)}**" if name == "all" else name, rate] +
                        [num(h[t], 1) for t in tables] + [f"**{h['total']:.1f}**",
                                                          percent(h["total"] / hours["all"]["total"])])
        lines += [f"**{precision}** precision, GPU-hours:", ""] + table(head, rows)
        lines += table4_lines(fig, steps4) + [""]
    return lines


def table4_lines(fig: dict, steps4: Optional[int]) -> list[str]:
    """What the target of Table 4 allows per pair-step, what the networks take, the slowest
    network against the others."""
    hours, tps = fig["hours"], fig["throughput"]
    allowed, summed = fig["table4_ms_per_pair_step_allowed"], fig["table4_ms_per_pair_step_summed"]
    ms = {name: 1000 / tp["attack"] for name, tp in tps.items()}
    slow = max(ms, key=ms.get)
    count = f" ({steps4:,} pair-steps per network)" if steps4 else ""
    lines = [f"Table 4{count}: {hours['all']['4']:.1f} GPU-hours for these {len(tps)} network(s). "
             f"The target of {fig['target_hours_table4']:g} hours allows {allowed:.1f} ms per "
             f"pair-step summed over the networks; they take {summed:.1f} ms, "
             f"{summed / allowed:.1f}x the target."]
    if len(ms) > 1:
        rest = summed - ms[slow]
        lines[0] += (f" The slowest, {slow}, takes {ms[slow]:.1f} ms per pair-step "
                     f"({hours[slow]['4']:.1f} h of Table 4, {ms[slow] / allowed:.1f}x the whole "
                     f"allowance); the other {len(ms) - 1} together {rest:.1f} ms "
                     f"({hours['all']['4'] - hours[slow]['4']:.1f} h, "
                     f"{rest / allowed:.1f}x the allowance).")
    return lines


def options_part(section: dict, sections: dict) -> list[str]:
    """Each option's throughput against the network's float32 figure of the tables section."""
    tables = sections.get("tables", {})
    measured = tables.get("measured", [])
    steps4 = table4_pair_steps(tables)

    def baseline(network: str) -> Optional[float]:
        for precision in ("float32", "paper"):
            for r in measured:
                if r["network"] == network and r["precision"] == precision and r.get("attack"):
                    return r["attack"]
        return None

    head = ["network", "precision", "options", "best batch", "pair-steps/s", "x float32",
            "GPU memory at best batch (GiB)", "flow against float32: max / RMS px (flow RMS)",
            "Table 4 GPU-hours at this rate", "stop"]
    rows = []
    for r in section.get("rows", []):
        rate, base = r.get("attack"), baseline(r["network"])
        best = r.get("batches", {}).get(str(r.get("best_batch")), {})
        diff = r.get("flow_difference")
        flow = DASH if not diff else \
            f"{diff['max_px']:.4f} / {diff['rms_px']:.4f} ({diff['flow_rms_px']:.2f})"
        stop = r.get("stop") or (f"skipped ({r['skipped']})" if "skipped" in r else
                                 f"failed: {r['failed']}" if "failed" in r else "")
        rows.append([r["network"], r["precision"], r.get("options", "-"), str(r.get("best_batch") or DASH),
                     num(rate), num(rate / base if rate and base else None, 2, "x"),
                     num(best.get("memory_gib"), 1), flow,
                     num(steps4 / rate / 3600 if rate and steps4 else None, 1), stop])
    right = [False, False, False, True, True, True, True, False, True, False]
    return ["Same random weights and frames; \"x float32\" against the network's float32 row of "
            "the throughput table (its paper row where the two are the same).", ""] + \
        table(head, rows, right)


def sampler_part(section: dict, _sections: dict) -> list[str]:
    rows = []
    for r in section.get("rows", []):
        if "failed" in r:
            rows.append([r["preset"], DASH, DASH, DASH, f"failed: {r['failed']}"])
            continue
        rows.append([r["preset"], str(r["count"]), num(r["cpu_s"] * 1000, 1), num(r["device_s"] * 1000, 1),
                     percent(r["identical_particles"])])
    return ["A pair's particles of each preset sampled on the CPU and on the GPU.", ""] + \
        table(["preset", "particles", "CPU ms per pair", "GPU ms per pair", "identical particles"], rows)


def training_part(section: dict, _sections: dict) -> list[str]:
    rows = []
    for r in section.get("rows", []):
        if "failed" in r:
            rows.append([r["what"], DASH, f"failed: {r['failed']}"])
            continue
        rows.append([r["what"], num(r["seconds"], 3), percent(r.get("share_of_training_step"))])
    return table(["what", "seconds", "share of the RAFT training step"], rows)


# -- make gpu-check ---------------------------------------------------------------------------------

def check_section(data: dict) -> list[str]:
    """``make gpu-check``'s section: its title, machine and tree, then a table per area."""
    lines = ["## make gpu-check", "", f"{data.get('title', 'gpu-check')}", ""]
    if data.get("machine"):
        lines.append(machine_line(data["machine"]))
    lines += [tree_line(data.get("tree")), ""]
    areas: dict[str, list[dict]] = {}
    for row in data.get("rows", []):
        areas.setdefault(row["area"], []).append(row)
    for area, rows in areas.items():
        lines += [f"### {area}", ""]
        lines += networks_table(rows) if area == "networks" else area_table(area, rows)
    return lines


def row_note(row: dict) -> str:
    return ("FAILED: " if row.get("failed") else "") + (row.get("note") or "")


def area_table(area: str, rows: list[dict]) -> list[str]:
    """The rows of one area (seconds: medians after a warm-up; memory: peak allocated), with a
    column of what follows from them for the training and attack-batch areas."""
    extra = {"training": ("share of the RAFT training step", training_share),
             "attack batch": ("gain over the smallest batch", batch_gain)}.get(area)
    head = ["what", "seconds", "GPU memory (GiB)"] + ([extra[0]] if extra else []) + ["note"]
    out = []
    for row in rows:
        cells = [row["what"], num(row.get("seconds"), 3), num(row.get("memory_gib"), 2)]
        out.append(cells + ([extra[1](row, rows)] if extra else []) + [row_note(row)])
    right = [False, True, True] + ([True] if extra else []) + [False]
    return table(head, out, right)


def training_share(row: dict, rows: list[dict]) -> str:
    """A weather row's seconds over the RAFT training step's (a dash for other rows)."""
    step = next((r.get("seconds") for r in rows if r["what"].startswith("raft training step")), None)
    if not row["what"].startswith("weather of") or not step or not row.get("seconds"):
        return DASH
    return percent(row["seconds"] / step)


_BATCH = re.compile(r"(\S+), batch of (\d+): a step$")


def batch_rate(row: dict) -> Optional[tuple[int, float]]:
    """``(batch, pair-steps per second)`` of an attack-batch row (None for another row)."""
    m = _BATCH.match(row["what"])
    if not m or not row.get("seconds"):
        return None
    return int(m[2]), int(m[2]) / row["seconds"]


def batch_gain(row: dict, rows: list[dict]) -> str:
    """A batch's pair-steps per second over the smallest batch's."""
    here, rates = batch_rate(row), [r for r in map(batch_rate, rows) if r]
    if not here or not rates:
        return DASH
    return f"{here[1] / min(rates)[1]:.2f}x"


def networks_table(rows: list[dict]) -> list[str]:
    """One line per network: forward and forward + backward (one pair), their memory."""
    nets: dict[str, dict[str, dict]] = {}
    for row in rows:
        name, _, what = row["what"].partition(", ")
        nets.setdefault(name, {})[what] = row
    out = []
    for name, got in nets.items():
        fwd, both = got.get("forward", {}), got.get("forward + backward", {})
        notes = "; ".join(n for n in (row_note(fwd), row_note(both)) if n)
        out.append([name, num(fwd.get("seconds"), 3), num(fwd.get("memory_gib"), 2),
                    num(both.get("seconds"), 3), num(both.get("memory_gib"), 2),
                    num(1 / both["seconds"] if both.get("seconds") else None, 1), notes])
    head = ["network", "forward s", "forward GiB", "forward + backward s", "forward + backward GiB",
            "forward + backward pairs/s", "note"]
    return ["One pair, 1024x436 unless the title says otherwise; seconds: medians after a warm-up; "
            "GiB: peak allocated GPU memory.", ""] + table(head, out, [False] + [True] * 5 + [False])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", nargs="?", type=Path, default=FOLDER,
                        help=f"the folder of {CHECK} and {SESSION} (default docs/figures)")
    args = parser.parse_args(argv)
    if not args.folder.is_dir():
        print(f"gpu_figures: {args.folder} is not a folder", file=sys.stderr)
        return 2
    print(f"wrote {write_folder(args.folder)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
