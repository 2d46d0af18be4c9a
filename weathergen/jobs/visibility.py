"""Which particles a pair's frames show, and the run's note on pairs whose frame 2 keeps few of
them: the render and attack jobs count and report them alike."""

from __future__ import annotations

from typing import Optional

from ..engine import LayeredParticles, visible_counts
from ..engine.weather.presets import list_presets
from ..words import counted

#: A pair of a paper preset whose frame 2 shows fewer than this fraction of the particle centres
#: frame 1 shows (strong camera motion, e.g. driving forward) is marked ``few_in_frame2`` in the
#: manifest, and the run says once that weather fields are the model for such motion.
FRAME2_KEPT_MIN = 0.5


def visibility_of(pair, particles) -> tuple[tuple[int, int], bool]:
    """The particle centres frames 1 and 2 show in front of the scene (over every layer of
    combined weather), and whether a paper preset's particles (a paper layer's) are
    :func:`few_in_frame2`."""
    layers = particles.layers if isinstance(particles, LayeredParticles) else (particles,)
    per_layer = [visible_counts(pair, r) for r in layers]
    visible = (sum(v[0] for v in per_layer), sum(v[1] for v in per_layer))
    return visible, any(r.optics is None and few_in_frame2(*v) for r, v in zip(layers, per_layer))


def few_in_frame2(visible1: int, visible2: int) -> bool:
    """Whether frame 2 shows fewer than :data:`FRAME2_KEPT_MIN` of the particle centres frame 1
    shows. The paper's model samples a pair's particles among the points visible in frame 1 or
    frame 2, in a box in front of camera 1: a camera that moves far into that box leaves most of
    them behind it or outside its view."""
    return visible2 < FRAME2_KEPT_MIN * visible1


def frame2_note(few: list[tuple[str, tuple[int, int]]], preset_name: str) -> Optional[str]:
    """The run's one line about the pairs it marked ``few_in_frame2`` (``few``: each one's name and
    visible counts in frames 1 and 2), or None when there are none. Render and attack print it."""
    if not few:
        return None
    order = ("snow", "rain", "sparks", "fog")
    fields = sorted((name for name in list_presets("field") if name.endswith("-moderate")),
                    key=lambda name: (order.index(name.split("-")[0])
                                      if name.split("-")[0] in order else len(order), name))
    worst, (v1, v2) = min(few, key=lambda f: f[1][1] / max(f[1][0], 1))
    share = v2 / max(v1, 1)
    return (f"in {counted(len(few), 'pair')} frame 2 shows fewer than half of the particles frame 1 "
            f"shows (strong camera motion; e.g. {worst}: {v2} of {v1}, {share:.0%}), marked "
            f"few_in_frame2 in the manifest. The paper's preset "
            f"'{preset_name}' places its particles in a box in front of camera 1; for strong "
            f"camera motion use a weather-field preset ({', '.join(fields)}, ...), whose "
            f"particles fill the world that both cameras see")


#: A frame whose depth is more than this share completed, or more than :data:`UNKNOWN_NOTE`
#: unknown (``--fill-gaps 0``), is counted in the run's one line about estimated depth.
COMPLETED_NOTE = 0.5
UNKNOWN_NOTE = 0.02


def depth_note(facts: list[tuple[str, dict]]) -> Optional[str]:
    """The run's one line about pairs whose depth is mostly estimated (``facts``: each written
    pair's name and the reader's facts, whose ``depth_provenance`` holds each frame's shares of
    measured, completed, sky and unknown depth), or None when no pair is."""
    worst = [(name, max(s["completed"] for s in f["depth_provenance"]),
              max(s["unknown"] for s in f["depth_provenance"]))
             for name, f in facts if f.get("depth_provenance")]
    worst = [w for w in worst if w[1] > COMPLETED_NOTE or w[2] > UNKNOWN_NOTE]
    if not worst:
        return None
    name, completed, unknown = max(worst, key=lambda w: (w[2], w[1]))
    return (f"in {counted(len(worst), 'pair')} more than {COMPLETED_NOTE:.0%} of a frame's depth "
            f"is completed or more than {UNKNOWN_NOTE:.0%} unknown (e.g. {name}: {completed:.0%} "
            f"completed, {unknown:.0%} unknown at the far depth); the weather there follows "
            f"{'estimated depth' if unknown <= UNKNOWN_NOTE else 'the far depth where it is unknown'}"
            f": see depth_provenance/ beside the depth and docs/datasets.md")
