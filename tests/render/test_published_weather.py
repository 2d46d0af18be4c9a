"""The paper's published weather: particle files in the research code's format, written here with
numpy as its ``save_weatherfile`` writes them (five float32 arrays, batch first), read, mapped into
a pair, drawn (the same frames as the same particles given directly, and a lone particle where
the research code's renderer puts it), inspected, attacked, evaluated; and the research code's
frame and scaling (its per-scene table, its camera translation zeroed in the scenes it scales)."""

from __future__ import annotations

import json
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from conftest import write_fake_sintel

from weathergen.datasets import load_scene_scales, open_dataset, reopen_dataset
from weathergen.engine import Particles, RenderSettings, load_preset, render_pair
from weathergen.engine.sampling.published import published_particles
from weathergen.errors import ConfigError, FormatError
from weathergen.io.images import read_image, to_uint8
from weathergen.io.published_weather import (PublishedWeather, is_published_set, published_file,
                                             read_published_weather)
from weathergen.render import published_preset

SIZE = (40, 64)
#: Sintel's research table scales alley_1 (by 2: its camera translation is zeroed), not bamboo_2.
SCENES = ("alley_1", "bamboo_2")
RESEARCH = ["--scene-scales", "research", "--no-translation-in-scaled-scenes"]


def invoke(args):
    from weathergen.cli.main import cli

    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


def blobs(n: int, side: int, rng) -> np.ndarray:
    """``n`` round flakes of varying width on ``side`` x ``side`` canvases (a few values below
    zero, as the research code's rotated flakes have). Shape: (n, side, side) float32."""
    y, x = np.mgrid[:side, :side] - side // 2
    widths = rng.uniform(0.6, side / 4, n)
    alpha = np.exp(-(x ** 2 + y ** 2)[None] / (2 * widths[:, None, None] ** 2))
    alpha[:, 0, 0] = -0.004
    return alpha.astype(np.float32)


def weather_arrays(seed: int, n: int = 40, side: int = 9) -> dict:
    """One pair's particles as the research code saves them: in front of camera 1 (in view),
    falling in camera 2's axes, their own flakes, colours and raw transparencies."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(0.8, 1.8, n)
    points = np.stack([rng.uniform(-1.4, 1.4, n) * z, rng.uniform(-0.9, 0.9, n) * z, z, np.ones(n)], 1)
    motion = np.stack([rng.normal(0, 0.01, n), rng.uniform(0.05, 0.1, n), rng.normal(0, 0.01, n),
                       np.zeros(n)], 1)
    flakes = np.zeros((1, n, 4, side, side), np.float32)
    flakes[0, :, 3] = blobs(n, side, rng)
    return {"points3D": points[None].astype(np.float32), "motion3D": motion[None].astype(np.float32),
            "flakes": flakes, "flakescol": rng.uniform(0.5, 1, (1, n, 3)).astype(np.float32),
            "flakestrans": rng.uniform(-2, 2, (1, n)).astype(np.float32)}


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    """A Sintel tree (two scenes of three frames, the camera moving) and a published set
    ``snow_npz`` with a file per pair, as the research code lays them out."""
    root = tmp_path_factory.mktemp("published")
    sintel = write_fake_sintel(root / "sintel", scenes=SCENES, frames=3, size=SIZE,
                               test_split=False)
    weather = root / "snow_npz"
    for s, scene in enumerate(SCENES):
        for frame in (1, 2):
            published_file(weather, scene, frame).parent.mkdir(parents=True, exist_ok=True)
            np.savez(published_file(weather, scene, frame), **weather_arrays(10 * s + frame))
    return sintel, weather


def research_dataset(sintel, scenes=SCENES):
    return open_dataset("sintel", sintel, scenes=list(scenes), scene_scales=load_scene_scales("research"),
                        camera_translation="unscaled")


# -- the research code's frame and scaling ------------------------------------------------------

def test_the_research_table_scales_its_scenes_and_zeroes_their_translation_only(tree):
    sintel, _ = tree
    plain = open_dataset("sintel", sintel)
    research = research_dataset(sintel)
    for ref in research.pairs()[::2]:
        a, b = plain.load(ref), research.load(ref)
        factor = 2.0 if ref.id.scene == "alley_1" else 1.0
        assert torch.allclose(b.depth1, factor * a.depth1)
        translation = b.cam2_from_cam1[:3, 3]
        if factor != 1.0:
            assert torch.all(translation == 0)                       # zeroed where scaled
        else:
            assert torch.allclose(translation, a.cam2_from_cam1[:3, 3])  # kept elsewhere
            assert translation.abs().max() > 0.05
        assert torch.allclose(b.cam2_from_cam1[:3, :3], a.cam2_from_cam1[:3, :3])
    assert load_scene_scales("research")["mountain_1"] == 0.05       # the bundled table
    # its scenes need not all be in a tree; the record of a run opens it again the same way
    again = reopen_dataset(research.describe())
    assert again.keeps_translation("alley_1") is False and again.keeps_translation("bamboo_2")
    with pytest.raises(ConfigError, match="no scene named"):        # a table of one's own is checked
        open_dataset("sintel", sintel, scene_scales={"mountain_1": 0.05})


# -- reading and mapping -------------------------------------------------------------------------

def test_a_file_reads_back_as_written_and_maps_into_the_pair_exactly(tree):
    sintel, weather = tree
    ds = research_dataset(sintel, ["alley_1"])
    pair = ds.load(ds.pairs()[0])
    arrays = weather_arrays(1)
    w = read_published_weather(published_file(weather, "alley_1", 1))
    assert w.count == 40 and w.side == 9 and np.array_equal(w.points, arrays["points3D"][0, :, :3])
    preset = load_preset("snow")
    p = published_particles(w, pair, preset)
    assert p.frame == "world" and p.stamps.shape == (40, 9, 9)
    x1 = arrays["points3D"][0].astype(np.float64)
    m = arrays["motion3D"][0, :, :3].astype(np.float64)
    # camera 1 sees the file's position; camera 2 the research code's R X1 + t + m
    c1, c2, rel = (t.numpy() for t in (pair.cam1_from_world, pair.cam2_from_world, pair.cam2_from_cam1))
    position = np.concatenate([p.position.double().numpy(), np.ones((40, 1))], 1)
    moved = np.concatenate([(p.position + p.motion).double().numpy(), np.ones((40, 1))], 1)
    np.testing.assert_allclose((position @ c1.T)[:, :3], x1[:, :3], atol=2e-6)
    np.testing.assert_allclose((moved @ c2.T)[:, :3], (x1 @ rel.T)[:, :3] + m, atol=2e-6)
    theta = 0.75 * (np.tanh(arrays["flakestrans"][0].astype(np.float64)) + 1) / 2   # s = snow's 0.75
    np.testing.assert_allclose(p.transparency.numpy(), theta, rtol=1e-6)
    assert np.array_equal(p.color.numpy(), arrays["flakescol"][0])
    assert np.array_equal(p.stamps.numpy(), np.maximum(arrays["flakes"][0, :, 3], 0))
    assert torch.all(p.offset1 == 0) and torch.all(p.offset2 == 0)
    assert p.settings == RenderSettings.from_preset(preset)


def test_a_lone_particle_lands_where_the_research_renderer_puts_it(tree):
    """One flake whose only non-zero pixel is its centre (value 1), at a sub-pixel position, on
    a still camera, added to the frame: the four pixels around it get θ · colour times the
    bilinear weights, the centre of a pixel being its integer coordinate (the research code's
    renderer's placement)."""
    sintel, _ = tree
    ds = open_dataset("sintel", sintel, scenes=["bamboo_2"])
    pair = ds.load(ds.pairs()[0])
    k = pair.intrinsics.numpy()
    u, v, z = 20.3, 11.6, 1.2
    x1 = np.array([(u - k[0, 2]) * z / k[0, 0], (v - k[1, 2]) * z / k[1, 1], z])
    alpha = np.zeros((1, 3, 3), np.float32)
    alpha[0, 1, 1] = 1
    w = PublishedWeather(
        points=x1[None].astype(np.float32), motion=np.zeros((1, 3), np.float32), alpha=alpha,
        color=np.array([[1.0, 0.5, 0.25]], np.float32), transparency=np.array([0.3], np.float32),
        path="lone")
    out = render_pair(pair, published_particles(w, pair, load_preset("snow", {"transparency": "1"})))
    added = (out.image1 - pair.image1[None])[0].double()
    theta = (np.tanh(0.3) + 1) / 2
    fu, fv = u - 20, v - 11
    for (row, col), weight in (((11, 20), (1 - fv) * (1 - fu)), ((11, 21), (1 - fv) * fu),
                               ((12, 20), fv * (1 - fu)), ((12, 21), fv * fu)):
        expected = theta * weight * np.array([1.0, 0.5, 0.25])
        clean = pair.image1[:, row, col].double().numpy()
        expected = np.minimum(clean + expected, 1) - clean
        np.testing.assert_allclose(added[:, row, col].numpy(), expected, atol=1e-5)
    added[:, 11:13, 20:22] = 0
    assert added.abs().max() < 1e-6                      # nothing anywhere else


@pytest.mark.parametrize("change, words", [
    (lambda a: a.pop("flakescol"), "no flakescol"),
    (lambda a: a.update(points3D=a["points3D"][:, :, :3]), "points3D must be (1, N, 4)"),
    (lambda a: a.update(motion3D=np.concatenate([a["motion3D"]] * 2)), "motion3D must be (1, 40, 4)"),
    (lambda a: a.update(flakes=a["flakes"][..., :8, :8]), "odd side"),
    (lambda a: a["points3D"].__setitem__((0, 3, 3), 2.0), "fourth (homogeneous) coordinate must be 1"),
    (lambda a: a["flakes"].__setitem__((0, 2, 0, 4, 4), 0.5), "colour offsets"),
    (lambda a: a["flakestrans"].__setitem__((0, 1), np.nan), "not finite"),
])
def test_every_bad_file_is_one_line_naming_it(change, words, tmp_path):
    arrays = weather_arrays(3)
    change(arrays)
    path = tmp_path / "frame_0001.npz"
    np.savez(path, **arrays)
    with pytest.raises(FormatError) as caught:
        read_published_weather(path)
    assert str(caught.value).startswith(str(path)) and words in str(caught.value)
    (tmp_path / "broken.npz").write_bytes(b"PK\x03\x04 not really")
    with pytest.raises(FormatError, match="not a readable .npz"):
        read_published_weather(tmp_path / "broken.npz")


def _truncated(path):
    path.write_bytes(path.read_bytes()[:300])


def _no_flakestrans(path):
    arrays = weather_arrays(1)
    arrays.pop("flakestrans")
    np.savez(path, **arrays)


@pytest.mark.parametrize("spoil, words", [
    (_truncated, "not a readable .npz file, truncated or damaged"),
    (lambda p: p.write_bytes(b""), "an empty file"),
    (lambda p: p.write_text("points3D = 1"), "not an .npz archive"),
    (_no_flakestrans, "not the research code's particle file: no flakestrans"),
])
def test_a_bad_first_or_only_file_of_a_set_is_named(spoil, words, tree, tmp_path):
    import shutil

    sintel, weather = tree
    for only in (False, True):
        copy = tmp_path / str(only) / "snow_npz"      # (the name says its preset)
        shutil.copytree(weather, copy)
        if only:                            # the set's only file
            for path in copy.glob("*/frame_*.npz"):
                if path != published_file(copy, "alley_1", 1):
                    path.unlink()
        first = published_file(copy, "alley_1", 1)
        spoil(first)
        assert is_published_set(copy)
        result = invoke(["render", "--root", sintel, "--particles", copy, "--scenes", "alley_1",
                         "--frames-per-scene", "1", "--out", tmp_path / f"out_{only}"])
        assert result.exit_code == 2
        assert f"{first}: {words}" in result.output and "manifest.json" not in result.output
    if spoil is _no_flakestrans:                # inspect names the missing array too
        shown = invoke(["inspect", first])
        assert shown.exit_code == 2 and f"{first}: not the research code's particle file: no " \
            f"flakestrans" in shown.output and "metadata_version" not in shown.output


def test_evaluate_of_a_set_writes_into_the_working_folder_by_default(tree):
    from weathergen.attack import default_evaluation_path

    _, weather = tree
    assert default_evaluation_path(weather, "raft", published=True) == \
        Path("evaluate-snow_npz-raft.json")
    assert default_evaluation_path(weather, "raft") == weather / "evaluate-raft.json"


def test_a_set_is_told_from_a_weathergen_folder_and_names_its_preset(tree, tmp_path):
    _, weather = tree
    assert is_published_set(weather) and not is_published_set(tmp_path)
    for folder, preset in (("particles_3000_npz", "particles-3000"), ("size_fog_png", "size-fog"),
                           ("color_additive_red_npz", "additive-red"), ("weather_rain", "rain"),
                           ("rain_1500_npz", "motion-blur-0.15"), ("my_weather", None)):
        assert published_preset(tmp_path / folder) == preset
    (tmp_path / "my_weather" / "alley_1").mkdir(parents=True)
    np.savez(tmp_path / "my_weather" / "alley_1" / "frame_0001.npz", **weather_arrays(1))
    result = invoke(["render", "--particles", tmp_path / "my_weather", "--out", tmp_path / "o"])
    assert result.exit_code == 2 and "name it with --preset" in result.output
    assert len(result.output.strip().splitlines()) == 1
    # evaluate takes the set with --weather, and says so (not render's --particles)
    result = invoke(["evaluate", "--weather", tmp_path / "my_weather", "--root", tree[0]])
    assert result.exit_code == 2 and result.output.startswith(
        f"Error: --weather {tmp_path / 'my_weather'}: published weather does not record")
    assert "name it with --preset" in result.output and "--particles" not in result.output


# -- the commands --------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def rendered(tree, tmp_path_factory):
    sintel, weather = tree
    out = tmp_path_factory.mktemp("render") / "r"
    result = invoke(["render", "--root", sintel, "--particles", weather, *RESEARCH,
                     "--format", "both", "--out", out])
    assert result.exit_code == 0, result.output
    return out, result.output


@pytest.mark.slow
def test_render_draws_the_files_as_the_same_particles_given_directly(tree, rendered):
    sintel, weather = tree
    out, output = rendered
    assert "Note:" not in output                      # opened in the research code's frame
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["preset_name"] == "snow"          # from the set's name, snow_npz
    preset = load_preset("snow")
    ds = research_dataset(sintel)
    for ref in ds.pairs():
        pair = ds.load(ref)
        arrays = weather_arrays(10 * SCENES.index(ref.id.scene) + ref.id.frame)
        # the same particles, written out here by hand in the pair's world frame
        x1 = np.concatenate([arrays["points3D"][0, :, :3].astype(np.float64), np.ones((40, 1))], 1)
        world = x1 @ np.linalg.inv(pair.cam1_from_world.numpy()).T
        motion = arrays["motion3D"][0, :, :3].astype(np.float64) @ pair.cam2_from_world.numpy()[:3, :3]
        n = 40
        direct = Particles(
            position=torch.from_numpy(world[:, :3]).float(), motion=torch.from_numpy(motion).float(),
            offset1=torch.zeros(n, 3), offset2=torch.zeros(n, 3),
            color=torch.from_numpy(arrays["flakescol"][0]),
            transparency=torch.from_numpy(0.75 * (np.tanh(arrays["flakestrans"][0].astype(np.float64))
                                                  + 1) / 2).float(),
            template=torch.zeros(n, dtype=torch.long), rotation=torch.zeros(n), scale=torch.ones(n),
            defocus=torch.zeros(n, dtype=torch.long), frame="world",
            settings=RenderSettings.from_preset(preset),
            stamps=torch.from_numpy(np.maximum(arrays["flakes"][0, :, 3], 0)))
        with torch.no_grad():
            expected = render_pair(pair, direct)
        name = f"{ref.id.scene}_{ref.id.frame:04d}"
        for k, img in ((1, expected.image1), (2, expected.image2)):
            written = read_image(out / "training" / "snow_clean" / name
                                 / f"frame_{ref.id.frame + k - 1:04d}.png")
            direct_png = to_uint8(img[0].permute(1, 2, 0).numpy())
            assert np.array_equal(to_uint8(written), direct_png), (name, k)
        # the output keeps every particle's stamp exactly
        stored = Particles.load(out / "training" / "particles" / name / f"frame_{ref.id.frame:04d}.npz")
        assert torch.equal(stored.stamps, direct.stamps)
        assert (expected.image1 != pair.image1[None]).float().mean() > 0.05   # weather drawn


@pytest.mark.slow
def test_the_output_renders_again_to_the_same_bytes(tree, rendered, tmp_path):
    sintel, _ = tree
    out, _ = rendered
    again = tmp_path / "again"
    result = invoke(["render", "--root", sintel, "--particles", out, *RESEARCH, "--out", again,
                     "--quiet"])
    assert result.exit_code == 0, result.output
    for png in (out / "training" / "snow_clean").rglob("*.png"):
        assert png.read_bytes() == (again / "training" / "snow_clean" / png.relative_to(
            out / "training" / "snow_clean")).read_bytes()


@pytest.mark.slow
def test_compat_reference_opens_the_research_frame(tree, rendered, tmp_path):
    """``--compat reference`` is the research code's frame and scaling: the same frames as the
    explicit options; the demo scene, whose scenes that table does not name, stays as it is."""
    from weathergen.datasets import in_research_frame

    sintel, weather = tree
    out, _ = rendered
    again = tmp_path / "compat"
    result = invoke(["render", "--root", sintel, "--particles", weather, "--compat", "reference",
                     "--out", again, "--quiet"])
    assert result.exit_code == 0 and "Note:" not in result.output, result.output
    for png in (out / "training" / "snow_clean").rglob("*.png"):
        assert png.read_bytes() == (again / png.relative_to(out)).read_bytes()
    demo = open_dataset("demo")
    assert in_research_frame(demo) is demo
    own = open_dataset("sintel", sintel, scene_scales={"bamboo_2": 3.0})
    assert in_research_frame(own).describe()["scene_scales"] == {"bamboo_2": 3.0}   # kept
    assert in_research_frame(own).keeps_translation("bamboo_2") is False


@pytest.mark.slow
def test_a_dataset_opened_otherwise_gets_a_note(tree, tmp_path):
    sintel, weather = tree
    result = invoke(["render", "--root", sintel, "--particles", weather, "--scenes", "bamboo_2",
                     "--frames-per-scene", "1", "--out", tmp_path / "o", "--quiet"])
    assert result.exit_code == 0
    assert "--scene-scales research --no-translation-in-scaled-scenes" in result.output


@pytest.mark.slow
def test_compat_reference_blends_alpha_motion_blur_sample_by_sample(tree, tmp_path):
    """A published α-blended set (``color_alpha_white``: 10 blur samples): under ``--compat
    reference`` each sample is blended over the frame the earlier ones left, as the research
    code draws it (the library's render of the record marked so); in the research frame without
    it, weathergen's blending (all samples at once). ``evaluate`` of the set measures the first."""
    sintel, _ = tree
    weather = tmp_path / "color_alpha_white_npz"
    published_file(weather, "alley_1", 1).parent.mkdir(parents=True)
    np.savez(published_file(weather, "alley_1", 1), **weather_arrays(5, n=60))
    select = ["--scenes", "alley_1", "--frames-per-scene", "1", "--quiet"]
    runs = {}
    for name, options in (("reference", ["--compat", "reference"]), ("paper", RESEARCH)):
        runs[name] = tmp_path / name
        result = invoke(["render", "--root", sintel, "--particles", weather, *options, *select,
                         "--out", runs[name]])
        assert result.exit_code == 0, result.output
    ds = research_dataset(sintel, ["alley_1"])
    pair = ds.load(ds.pairs()[0])
    record = published_particles(read_published_weather(published_file(weather, "alley_1", 1)),
                                 pair, load_preset("alpha-white"))
    assert record.settings.blur_samples == 10 and record.settings.blur_blend == "sum"
    ordered = record.for_compat("reference")
    pngs = {}
    for name, drawn in (("reference", ordered), ("paper", record)):
        with torch.no_grad():
            expected = render_pair(pair, drawn)
        written = read_image(runs[name] / "training" / "alpha-white_clean" / "alley_1_0001"
                             / "frame_0001.png")
        pngs[name] = to_uint8(written)
        assert np.array_equal(pngs[name], to_uint8(expected.image1[0].permute(1, 2, 0).numpy()))
    assert not np.array_equal(pngs["reference"], pngs["paper"])      # the streaks overlap
    stored = Particles.load(runs["reference"] / "training" / "particles" / "alley_1_0001"
                            / "frame_0001.npz")
    assert stored.settings == ordered.settings                       # kept in the output
    manifest = json.loads((runs["reference"] / "manifest.json").read_text())
    assert manifest["compat"] == "reference"
    (tmp_path / "tiny.py").write_text(TINY)
    model = ["--model", f"{tmp_path / 'tiny.py'}:build", "--quiet"]
    figures = []
    for source, extra in ((weather, ["--root", sintel]), (runs["reference"], [])):
        path = tmp_path / f"{len(figures)}.json"
        result = invoke(["evaluate", "--weather", source, *extra, *model, "--json", path])
        assert result.exit_code == 0, result.output
        figures.append(json.loads(path.read_text())["pairs"][0]["aee_weather"])
    assert figures[0] == pytest.approx(figures[1], rel=1e-6)


def test_inspect_shows_a_published_file(tree):
    _, weather = tree
    result = invoke(["inspect", published_file(weather, "alley_1", 1)])
    assert result.exit_code == 0, result.output
    for words in ("research code", "scene alley_1", "particles", "40", "9 px square",
                  "θ / s"):
        assert words in result.output


TINY = textwrap.dedent('''
    import torch
    from torch import nn

    def build():
        torch.manual_seed(0)
        conv = nn.Conv2d(6, 2, 3, padding=1)

        class Net(nn.Module):
            def __init__(self):
                super().__init__()
                self.conv = conv

            def forward(self, image1, image2):
                return 5 * self.conv(torch.cat([image1, image2], 1))
        return Net()
''')


@pytest.mark.slow
def test_attack_starts_from_the_published_particles(tree, tmp_path):
    sintel, weather = tree
    (tmp_path / "tiny.py").write_text(TINY)
    out = tmp_path / "a"
    result = invoke(["attack", "--root", sintel, "--particles", weather, *RESEARCH, "--scenes",
                     "alley_1", "--frames-per-scene", "1", "--model", f"{tmp_path / 'tiny.py'}:build",
                     "--steps", "2", "--compat", "reference", "--out", out, "--quiet"])
    assert result.exit_code == 0, result.output
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["config"]["particles_from"] == str(weather)
    assert manifest["preset_name"] == "snow"
    best = Particles.load(out / "training" / "particles" / "alley_1_0001" / "frame_0001.npz")
    ds = research_dataset(sintel, ["alley_1"])
    start = published_particles(read_published_weather(published_file(weather, "alley_1", 1)),
                                ds.load(ds.pairs()[0]), load_preset("snow"))
    assert torch.equal(best.stamps, start.stamps)                   # the flakes stay the file's
    assert torch.allclose(best.position, start.position, atol=1e-3)  # positions are not optimised
    assert (best.offset1 - start.offset1).abs().max() < 0.05        # the offsets are, a little
    # step 0 is the published weather itself: its figures are those of evaluate on the set
    log = (out / "training" / "attack_log" / "alley_1_0001.csv").read_text().splitlines()
    assert log[0].startswith("step") and log[1].startswith("0,")


@pytest.mark.slow
def test_evaluate_measures_the_set_as_render_then_evaluate_does(tree, rendered, tmp_path):
    sintel, weather = tree
    out, _ = rendered
    (tmp_path / "tiny.py").write_text(TINY)
    model = ["--model", f"{tmp_path / 'tiny.py'}:build"]
    direct = invoke(["evaluate", "--weather", weather, "--root", sintel, *model, "--json",
                     tmp_path / "set.json", "--quiet"])
    assert direct.exit_code == 0, direct.output
    via = invoke(["evaluate", "--weather", out, *model, "--json", tmp_path / "render.json",
                  "--quiet"])
    assert via.exit_code == 0, via.output
    a, b = (json.loads((tmp_path / f).read_text()) for f in ("set.json", "render.json"))
    assert a["published"] == {"preset": "snow"} and len(a["pairs"]) == 4
    for row_a, row_b in zip(a["pairs"], b["pairs"]):
        assert row_a["aee_weather"] == pytest.approx(row_b["aee_weather"], rel=1e-6)
        assert row_a["weather_coverage"] == pytest.approx(row_b["weather_coverage"])
    missing = invoke(["evaluate", "--weather", weather, *model])
    assert missing.exit_code == 2 and "give the clean dataset with --root" in missing.output


def test_stored_stamps_are_refused_on_a_weather_field_and_of_the_wrong_shape(tree):
    from weathergen.engine.rendering.renderer import check_stored_stamps

    sintel, weather = tree
    ds = research_dataset(sintel, ["alley_1"])
    p = published_particles(read_published_weather(published_file(weather, "alley_1", 1)),
                            ds.load(ds.pairs()[0]), load_preset("snow"))
    with pytest.raises(ConfigError, match="S odd"):
        check_stored_stamps(p.replace(stamps=p.stamps[:, :8, :8]))
    with pytest.raises(ConfigError, match="N = 40"):
        check_stored_stamps(p.replace(stamps=p.stamps[:3]))
