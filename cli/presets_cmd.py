"""``weathergen presets``: list the bundled presets, or show one fully resolved."""

from __future__ import annotations

import click
from rich.console import Console
from rich.table import Table

from weathergen.engine.weather.atmosphere import extinction_visibility
from weathergen.engine.weather.preset_groups import preset_groups
from weathergen.engine.weather.presets import (EXAMPLE_COMBINATIONS, LAYER_JOIN, CombinedPreset,
                                               FieldPreset, field_preset_keys, load_preset,
                                               parse_set_options, preset_keys)

from .options import STOPPED, exit_codes

#: The keys of a field preset that apply to an atmosphere alone (density 0, no particles): its
#: air, and the wind and frame rate that drift a heterogeneous one.
ATMOSPHERE_KEYS = ("description", "density", "wind", "frame_rate", "visibility", "rain_rate",
                   "snow_rate", "heterogeneity", "heterogeneity_scale", "airlight", "sky_distance")
#: Where ``weathergen presets NAME`` shows the visibility of the air as rendered.
_VEIL_AFTER = "snow_rate"


@click.command("presets", epilog=exit_codes(("0", "listed or shown"),
                                             ("2", "an unknown preset, or a bad override (one line)"),
                                             STOPPED))
@click.argument("name", required=False)
@click.option("--set", "overrides", multiple=True, metavar="[LAYER.]KEY=VALUE",
              help="Override one preset key (repeatable), e.g. --set count=500; in a combined "
                   "preset name the layer by name or position: --set fog-light.density=0.05, "
                   "--set 2.density=0.05.")
def presets_command(name, overrides):
    """List the weather presets, or show preset NAME (a name, a .toml file, or presets joined by +
    such as rain-heavy+fog-light) fully resolved.

    The list groups the paper's four weathers (snow, rain, sparks, fog), its ablation variants
    (its other particle configurations, each varying one parameter), the weather fields' severity
    ladders and example combinations."""
    console = Console(width=160)
    sets = parse_set_options(overrides)
    if name is None:
        models = {"paper": (preset_keys(), "paper model: visible particles per 1024x436 pair "
                                           "(scaled by frame area), sizes in pixels"),
                  "field": (field_preset_keys(), "field model: a weather field in scene units "
                                                 "(metres on metric data), density per m³")}
        for group in preset_groups():
            keys, model_text = models[group.model]
            columns = [f.name for f in keys if f.metadata.get("main")]
            table = Table(title=f"{group.title}; {model_text}", header_style="bold",
                          caption=_FIELD_CAPTION if group.model == "field" else None)
            table.add_column("name", no_wrap=True)  # names are what users type: never cut them
            if group.varies:
                table.add_column("varies", no_wrap=True)
            for col in columns:
                table.add_column(_HEADERS.get(col, col.replace("_", " ")), justify="right",
                                 no_wrap=True)
            for i, preset_name in enumerate(group.names):
                p = load_preset(preset_name, overrides=sets if group.model == "paper" else {})
                varies = (group.varies[i],) if group.varies else ()
                table.add_row(preset_name, *varies, *(_main_value(p, c) for c in columns))
            console.print(table)
        table = Table(title=f"combined presets, examples: any presets of either model joined by "
                            f"{LAYER_JOIN}, one layer each", header_style="bold")
        for col in ("name", "layers", "description"):
            table.add_column(col, no_wrap=col != "description")
        for combined_name, description in EXAMPLE_COMBINATIONS.items():
            c = load_preset(combined_name)
            layers = f" {LAYER_JOIN} ".join(f"{n} ({m})" for n, m in zip(c.layer_names, c.layer_models))
            table.add_row(combined_name, layers, description)
        console.print(table)
        return
    p = load_preset(name, overrides=sets)
    layers = p.layers if isinstance(p, CombinedPreset) else (p,)
    for i, layer in enumerate(layers, 1):
        _show(console, layer, f"layer {i} of {p.name}: " if len(layers) > 1 else "")


def _show(console: Console, p, title: str) -> None:
    """One preset's every key, its value and its meaning, and where it came from."""
    field_model = isinstance(p, FieldPreset)
    table = Table(title=f"{title}preset {p.name} ({'field' if field_model else 'paper'} model)",
                  header_style="bold")
    table.add_column("key")
    table.add_column("value")
    table.add_column("meaning")
    table.add_row("model", "field" if field_model else "paper",
                  "field: weather field in scene units; paper: the paper's per-pair model")
    for f in (field_preset_keys() if field_model else preset_keys()):
        if _applies(p, f.name):
            table.add_row(f.name, _fmt(getattr(p, f.name)), f.metadata.get("doc", ""))
        if field_model and f.name == _VEIL_AFTER:
            table.add_row("(veil)", f"{extinction_visibility(p.extinction):.0f} m (β₀ "
                          f"{1000 * p.extinction:.3g} /km)" if p.has_atmosphere else "clear air",
                          "visibility of the air as rendered: -ln(0.05) / β₀, β₀ the extinction "
                          "of visibility, rain_rate and snow_rate together")
    console.print(table)
    if field_model and p.density == 0:
        console.print("an atmosphere alone (density 0): the particle keys do not apply and are "
                      "left out", markup=False, highlight=False)
    console.print(f"source: {p.source}", markup=False, highlight=False)


# Short headers for the listing, so that a row fits on one line of 160 columns.
_HEADERS = {"depth_decay": "d-decay", "transparency": "θ", "motion_y": "m_y",
            "fall_speed": "fall m/s", "exposure": "exposure s", "diameter": "diameter",
            "motion_blur": "blur", "blur_length": "blur length", "blur_samples": "blur K"}


_FIELD_CAPTION = ("visibility: of the air as rendered, rain and snow included; –: a particle "
                  "key, which an atmosphere alone does not use")


def _applies(p, key: str) -> bool:
    """Whether preset ``p`` uses ``key``: every key but the particles' in an atmosphere alone."""
    return not isinstance(p, FieldPreset) or p.density > 0 or key in ATMOSPHERE_KEYS


def _main_value(p, key: str) -> str:
    if not _applies(p, key):
        return "–"
    if key == "visibility":
        return f"{extinction_visibility(p.extinction):.0f}" if p.has_atmosphere else "clear"
    if key == "transparency" and getattr(p, "transparency_mode", "") == "constant":
        return f"{_fmt(p.transparency)} const"  # not scaled by the depth hat
    return _fmt(getattr(p, key))


def _fmt(value) -> str:
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, tuple):
        return "(" + ", ".join(_fmt(v) for v in value) + ")"
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)
