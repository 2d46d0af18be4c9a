"""Dataset readers, looked up by name. Each turns files on disk into :class:`FramePair` records.

>>> ds = open_dataset("sintel", root="/data/MPI-Sintel", frames_per_scene=5)   # Sintel-tr115
>>> pair = ds.load(ds.pairs()[0])
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

from ..errors import ConfigError
from .base import Dataset, NativeFlow, PairRef, Selection
from .custom import CustomDataset
from .demo import demo_root
from .kitti import KittiDataset
from .sintel import SintelDataset, load_scene_scales
from .spring import SpringDataset
from .stereo import RightCamera


class DemoDataset(SintelDataset):
    """The bundled demo scene (Sintel layout, generated on first use into the user cache)."""

    name = "demo"
    default_world_up = "+z"          # the demo world is z-up, like the Blender scenes behind Sintel

    def __init__(self, root=None, selection: Selection = Selection(), **options):
        super().__init__(root if root is not None else demo_root(), selection, **options)


#: name -> reader class; every reader takes ``(root, selection, **options)``.
DATASETS: dict[str, type[Dataset]] = {
    "custom": CustomDataset,
    "demo": DemoDataset,
    "kitti": KittiDataset,
    "sintel": SintelDataset,
    "spring": SpringDataset,
}


def frame_rate_of(name: str) -> float:
    """The frame rate of the reader registered as ``name`` (a pair's ``id.dataset``); a name not
    registered gets :attr:`Dataset.frame_rate`'s default."""
    return DATASETS.get(name, Dataset).frame_rate


def frame_rates_text() -> str:
    """The readers' frame rates in words, readers of one rate together, e.g. ``"sintel, spring,
    demo 24; kitti 10; custom 30"`` (for help texts: the rates live on the reader classes)."""
    by_rate: dict[float, list[str]] = {}
    for name, cls in DATASETS.items():
        by_rate.setdefault(cls.frame_rate, []).append(name)
    return "; ".join(f"{', '.join(names)} {rate:g}" for rate, names in by_rate.items())


def right_camera(dataset: Dataset, pair) -> RightCamera:
    """The right camera of ``pair`` (:mod:`weathergen.datasets.stereo`), read by the reader's own
    :meth:`~Dataset.right_camera`; ConfigError for a reader without a second camera (its
    :attr:`~Dataset.stereo` is False), naming the readers with one; DatasetError naming a
    missing file."""
    if not dataset.stereo:
        readers = [name for name, cls in DATASETS.items() if cls.stereo]
        raise ConfigError(f"dataset {dataset.name!r} has no second camera; stereo rendering reads "
                          f"{', '.join(readers)} (KITTI image_3, Spring's right view, the custom "
                          "layout's right/ folder)")
    return dataset.right_camera(pair)


def default_dataset(root: Optional[str | Path]) -> str:
    """The reader used when none is named: the bundled ``demo`` without a root, ``sintel`` with one."""
    return "sintel" if root else "demo"


def open_dataset(name: str, root: Optional[str | Path] = None, *, split: str = "training",
                 pass_: str = "clean", scenes=None, from_scene=None, frames_per_scene=None,
                 first_frame=None, **options) -> Dataset:
    """Open a dataset by name with a selection of pairs; reader-specific ``options`` pass through.

    Unknown names raise :class:`ConfigError` listing the known ones. ``root`` may be omitted only
    for ``demo``.
    """
    try:
        cls = DATASETS[name]
    except KeyError:
        raise ConfigError(f"unknown dataset {name!r}; known: {', '.join(sorted(DATASETS))}") from None
    if root is None and name != "demo":
        raise ConfigError(f"dataset {name!r} needs ${{root}}, the folder it is stored in")
    selection = Selection(split=split, pass_=pass_, scenes=tuple(scenes) if scenes else None,
                          from_scene=from_scene, frames_per_scene=frames_per_scene,
                          first_frame=first_frame)
    dataset = cls(root, selection, **options)
    if hasattr(dataset, "check_scene_scales"):
        dataset.check_scene_scales()
    return dataset


#: Entries of :meth:`Dataset.describe` that are the name, root and selection; the others are the
#: reader's own options.
_SELECTION_KEYS = ("dataset", "root", "split", "pass", "scenes", "from_scene", "frames_per_scene",
                   "first_frame")


def reopen_dataset(description: dict) -> Dataset:
    """Open the dataset a :meth:`Dataset.describe` dictionary (as kept in manifests) names.

    Every reader option recorded there (depth scales, far depth, ...) is applied again, so the
    pairs load exactly as they did for the run that recorded it.
    """
    try:
        name = description["dataset"]
    except (KeyError, TypeError):
        raise ConfigError("the recorded input does not name its dataset") from None
    options = {k: v for k, v in description.items() if k not in _SELECTION_KEYS}
    return open_dataset(name, None if name == "demo" else description.get("root"),
                        split=description.get("split", "training"), pass_=description.get("pass", "clean"),
                        scenes=description.get("scenes"), from_scene=description.get("from_scene"),
                        frames_per_scene=description.get("frames_per_scene"),
                        first_frame=description.get("first_frame"), **options)


def in_research_frame(dataset: Dataset) -> Dataset:
    """``dataset`` opened in the frame and scaling of the paper's research code (what
    ``--compat reference`` opens): its per-scene depth factors (the bundled ``research`` table,
    unless the dataset has a table of its own) and the camera translation zeroed in the scenes
    they scale (unless the dataset zeroes it everywhere). A dataset none of whose scenes that
    changes (the demo, KITTI, a tree without Sintel's scene names) is returned as it is."""
    description = dataset.describe()
    if "scene_scales" not in description:
        return dataset
    table = description.get("scene_scales") or load_scene_scales("research")
    scenes = dataset.all_scenes() or []
    if not any(table.get(scene, 1.0) != 1.0 for scene in scenes):
        return dataset
    if not description.get("scene_scales"):
        description.update(scene_scales=table, scene_scales_bundled=True)
    if description.get("camera_translation") is True:
        description["camera_translation"] = "unscaled"
    return reopen_dataset(description)


def demo_pairs(**selection) -> list:
    """Every selected pair of the demo scene, loaded (a convenience for examples and tests)."""
    ds = open_dataset("demo", **selection)
    return [ds.load(ref) for ref in ds.pairs()]


__all__ = ["DATASETS", "frame_rates_text", "CustomDataset", "Dataset", "DemoDataset", "KittiDataset", "NativeFlow",
           "PairRef", "RightCamera", "Selection", "SintelDataset", "SpringDataset", "default_dataset", "demo_pairs",
           "frame_rate_of", "in_research_frame", "load_scene_scales", "open_dataset", "reopen_dataset",
           "right_camera"]
