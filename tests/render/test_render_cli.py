"""`weathergen render` end to end: outputs, determinism, sharding, resumption, re-rendering, errors."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from weathergen.cli.main import _register, cli
from weathergen.datasets import open_dataset
from weathergen.engine.records.particles import FORMAT_VERSION, _coded, _decoded
from weathergen.io.images import read_image
from weathergen.outputs import read_metadata


def stored_values(arrays: dict, name: str) -> np.ndarray:
    """The values a particle file's array ``name`` stands for (codes decoded), for display.
    Shape: as the record holds it ((N, 3) for motion whatever the storage)."""
    if _coded(arrays):
        return _decoded(arrays, name, int(arrays.get("format_version", FORMAT_VERSION)),
                        "<arrays>").astype(np.float64)
    return arrays[name].astype(np.float64)


# Small and quick: a few hundred particles on the street scene's first two pairs.
FAST = ("--scenes", "street", "--frames-per-scene", "2", "--set", "count=300")

#: Every test here runs whole commands on the demo scene.
pytestmark = pytest.mark.slow


def run(*args):
    _register()
    return CliRunner().invoke(cli, [str(a) for a in args])


def digests(root: Path, pattern: str = "*.png") -> dict:
    """sha256 of every frame and metadata file below root, by relative path."""
    out = {}
    for p in sorted(root.rglob("*")):
        if p.is_file() and (p.match(pattern) or p.suffix == ".npz"):
            out[str(p.relative_to(root))] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


@pytest.fixture(scope="module")
def snow_run(tmp_path_factory, demo_root):
    out = tmp_path_factory.mktemp("render") / "snow"
    res = run("render", "--out", out, *FAST)
    assert res.exit_code == 0, res.output
    return out


def test_outputs_layout_and_manifest(snow_run):
    files = digests(snow_run)
    assert "training/snow_clean/street_0001/frame_0001.png" in files
    assert "training/snow_clean/street_0001/frame_0002.png" in files
    assert "training/particles/street_0002/frame_0002.npz" in files
    manifest = json.loads((snow_run / "manifest.json").read_text())
    assert manifest["preset_name"] == "snow"
    assert manifest["preset"]["count"] == 300
    assert manifest["summary"] == {"written": 2, "skipped": 0, "failed": 0}
    assert set(manifest["pairs"]) == {"demo:training:street:1", "demo:training:street:2"}
    assert all(p["seed"] > 0 for p in manifest["pairs"].values())
    assert manifest["input"]["dataset"] == "demo"
    assert manifest["runs"][0]["command"] == ["weathergen", "render", "--out", str(snow_run), *FAST]


def test_weather_changes_frames_and_output_reads_back_as_sintel(snow_run, demo_root):
    ds = open_dataset("sintel", snow_run, pass_="snow_clean")
    refs = ds.pairs()
    assert [r.id.scene for r in refs] == ["street_0001", "street_0002"]
    pair = ds.load(refs[0])
    original = open_dataset("demo", scenes=["street"]).load(open_dataset("demo", scenes=["street"]).pairs()[0])
    # the geometry came along unchanged; the frames gained bright particles
    np.testing.assert_allclose(pair.depth1.numpy(), original.depth1.numpy())
    np.testing.assert_allclose(pair.flow.numpy(), original.flow.numpy())
    diff = (pair.image1 - original.image1).mean(0)
    assert (diff > 0.02).float().mean() > 0.01, "snow should brighten part of the frame"
    assert (diff < -1 / 255).float().mean() < 0.01, "additive snow never darkens"


def test_metadata_is_small_and_self_describing(snow_run):
    meta_file = snow_run / "training/particles/street_0001/frame_0001.npz"
    arrays = read_metadata(meta_file)
    assert arrays["position"].shape == (300, 3)
    assert str(arrays["pair_scene"]) == "street" and int(arrays["pair_frame"]) == 1
    assert 0 < int(arrays["visible1"]) <= 300
    assert meta_file.stat().st_size < 200_000 * 300 / 3000
    res = run("inspect", meta_file)
    assert res.exit_code == 0 and "street frame 1" in res.output and "300" in res.output


def test_same_seed_same_bytes_other_seed_differs(snow_run, tmp_path):
    again = tmp_path / "again"
    assert run("render", "--out", again, *FAST).exit_code == 0
    assert digests(again) == digests(snow_run)
    other = tmp_path / "other"
    assert run("render", "--out", other, "--seed", "1", *FAST).exit_code == 0
    assert digests(other) != digests(snow_run)


@pytest.mark.parametrize("option", [("--workers", "2"), ("--batch-size", "2")])
def test_workers_and_batches_do_not_change_bytes(snow_run, tmp_path, option):
    out = tmp_path / "other"
    res = run("render", "--out", out, *option, *FAST)
    assert res.exit_code == 0, res.output
    assert digests(out) == digests(snow_run)


def test_two_shards_equal_one_run(snow_run, tmp_path):
    out = tmp_path / "sharded"
    for shard in ("1/2", "2/2"):
        res = run("render", "--out", out, "--shard", shard, *FAST)
        assert res.exit_code == 0, res.output
    assert digests(out) == digests(snow_run)
    manifest = json.loads((out / "manifest.json").read_text())
    assert len(manifest["pairs"]) == 2 and len(manifest["shards"]) == 2


def test_rerender_from_metadata_is_bit_identical(snow_run, tmp_path):
    out = tmp_path / "again"
    res = run("render", "--out", out, "--particles", snow_run, *FAST[:4])
    assert res.exit_code == 0, res.output
    assert digests(out) == digests(snow_run)


def test_rerender_onto_final_pass_and_with_alpha_blending(snow_run, tmp_path):
    final = tmp_path / "final"
    assert run("render", "--out", final, "--particles", snow_run, "--pass", "final", *FAST[:4]).exit_code == 0
    a = read_image(snow_run / "training/snow_clean/street_0001/frame_0001.png")
    b = read_image(final / "training/snow_final/street_0001/frame_0001.png")
    assert not np.array_equal(a, b)
    alpha = tmp_path / "alpha"
    res = run("render", "--out", alpha, "--particles", snow_run, "--set", "blend=alpha", *FAST[:4])
    assert res.exit_code == 0, res.output
    c = read_image(alpha / "training/snow_clean/street_0001/frame_0001.png")
    assert not np.array_equal(a, c)
    res = run("render", "--out", tmp_path / "x", "--particles", snow_run, "--set", "count=5", *FAST[:4])
    assert res.exit_code == 2 and "fixed by the stored particles" in res.output


def test_exr_output_has_opacity(tmp_path):
    from weathergen.io.exr import read_exr

    out = tmp_path / "exr"
    res = run("render", "--out", out, "--format", "both", *FAST[:4], "--frames-per-scene", "1",
              "--set", "count=300")
    assert res.exit_code == 0, res.output
    channels = read_exr(out / "training/snow_clean_exr/street_0001/frame_0001.exr")
    png = read_image(out / "training/snow_clean/street_0001/frame_0001.png")
    assert channels["RGB"].shape == png.shape
    assert np.abs(np.clip(channels["RGB"], 0, 1) - png).max() <= 0.5 / 255 + 1e-6
    assert channels["opacity"].max() > 0.1 and channels["opacity"].min() == 0


def test_resume_after_kill_gives_identical_bytes(snow_run, tmp_path):
    out = tmp_path / "killed"
    script = Path(sys.executable).parent / "weathergen"
    proc = subprocess.Popen([str(script), "render", "--out", str(out), "-q", *FAST],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=os.environ)
    first = out / "training/particles/street_0001/frame_0001.npz"
    deadline = time.time() + 120
    while not first.exists() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    # whatever the kill interrupted is under a hidden temporary name; every final name is whole
    for p in out.rglob("*.png"):
        if not p.name.startswith("."):
            read_image(p)
    res = run("render", "--out", out, *FAST)
    assert res.exit_code == 2 and "--resume" in res.output
    res = run("render", "--out", out, "--resume", *FAST)
    assert res.exit_code == 0, res.output
    assert digests(out) == digests(snow_run)
    assert not [p for p in out.rglob(".*") if p.is_file() and ".tmp" in p.name]
    res = run("render", "--out", out, "--resume", *FAST)
    assert res.exit_code == 0, res.output
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["runs"][-1]["skipped"] == 2


@pytest.mark.parametrize("signum,workers", [(signal.SIGINT, "2"), (signal.SIGTERM, "1")],
                         ids=["ctrl-c-workers-2", "kill-term"])
def test_interrupt_stops_cleanly_and_resume_finishes(snow_run, tmp_path, signum, workers):
    out = tmp_path / "stopped"
    script = Path(sys.executable).parent / "weathergen"
    # a shell may start us with Ctrl-C ignored, which the child would inherit
    proc = subprocess.Popen([str(script), "render", "--out", str(out), "--workers", workers, *FAST],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=os.environ,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.time() + 120
    while not list(out.rglob("*.npz")) and proc.poll() is None and time.time() < deadline:
        time.sleep(0.02)
    proc.send_signal(signum)
    output = proc.communicate(timeout=60)[0].decode()
    if proc.returncode == 0:
        pytest.skip("the run finished before the signal arrived")
    assert proc.returncode == 128 + signum, output
    assert "Traceback" not in output and "--resume" in output
    assert not [p for p in out.rglob(".*") if ".tmp" in p.name]
    # every pair on disk is in the manifest: the pairs in progress finished and were recorded
    manifest = json.loads((out / "manifest.json").read_text())
    written = {k for k, p in manifest["pairs"].items() if p["status"] == "written"}
    assert len(written) == len(list(out.rglob("*.npz"))) >= 1
    res = run("render", "--out", out, "--resume", *FAST)
    assert res.exit_code == 0, res.output
    assert digests(out) == digests(snow_run)


@pytest.mark.parametrize("batch", ["1", "4"])
def test_fake_sintel_with_a_corrupt_pair(fake_sintel, tmp_path, batch):
    (fake_sintel / "training/depth/bamboo/frame_0002.dpt").write_bytes(b"junk")
    out = tmp_path / "out"
    res = run("render", "--root", fake_sintel, "--out", out, "--set", "count=50", "--batch-size", batch)
    assert res.exit_code == 1
    assert "frame_0002.dpt" in res.output and "failed" in res.output
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["summary"] == {"written": 4, "skipped": 0, "failed": 2}
    # nothing of the failed pairs was written
    assert not (out / "training/snow_clean/bamboo_0002").exists()
    assert (out / "training/snow_clean/alley_0003/frame_0004.png").exists()


@pytest.mark.parametrize("args,message", [
    (("--preset", "hail"), "unknown preset 'hail'"),
    (("--set", "colour=1"), "colour"),
    (("--set", "count=-3"), "count"),
    (("--shard", "3/2"), "I must be between 1 and N"),
    (("--shard", "x"), "expected I/N"),
    (("--device", "cuda:7"), "not available"),
])
def test_bad_options(tmp_path, args, message):
    res = run("render", "--out", tmp_path / "o", *args)
    assert res.exit_code == 2, res.output
    assert message in res.output
    assert not (tmp_path / "o").exists()


def test_refuses_foreign_non_empty_folder(tmp_path):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "thesis.tex").write_text("keep me")
    res = run("render", "--out", out, *FAST)
    assert res.exit_code == 2 and "not created by weathergen render" in res.output
    assert sorted(p.name for p in out.iterdir()) == ["thesis.tex"]


def test_unwritable_output(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    res = run("render", "--out", blocker / "sub", *FAST)
    assert res.exit_code == 2 and "cannot write" in res.output


def test_metadata_from_another_scene_or_future_version(snow_run, tmp_path):
    import shutil

    src = tmp_path / "src"
    shutil.copytree(snow_run, src)
    a = src / "training/particles/street_0001/frame_0001.npz"
    b = src / "training/particles/street_0002/frame_0002.npz"
    shutil.copy(b, a)                     # pair 1 now holds pair 2's particles
    res = run("render", "--out", tmp_path / "o1", "--particles", src, *FAST[:4])
    assert res.exit_code == 1 and "belongs to street frame 2" in res.output
    arrays = dict(np.load(b))
    arrays["metadata_version"] = np.array(99, np.int32)
    np.savez(b, **arrays)
    res = run("render", "--out", tmp_path / "o2", "--particles", src, *FAST[:4])
    # now both pairs fail (pair 1 as before): nothing to show, exit 2 and no output folder
    assert res.exit_code == 2 and "newer than this weathergen" in res.output
    assert "every selected pair failed" in res.output and not (tmp_path / "o2").exists()


def test_preview_writes_a_contact_sheet(snow_run, tmp_path):
    out = tmp_path / "sheet.png"
    res = run("preview", snow_run, "--out", out, "--width", "128")
    assert res.exit_code == 0, res.output
    sheet = read_image(out)
    assert sheet.shape[1] == 3 * 128 and sheet.shape[0] > 50


def test_kitti_render_keeps_sparse_flow_validity(tmp_path, demo_root):
    from fake_datasets import demo_sequence, write_fake_kitti

    street = demo_sequence("street")[1]
    write_fake_kitti(tmp_path / "kitti", street[0], scene="000004")
    out = tmp_path / "out"
    res = run("render", "--dataset", "kitti", "--root", tmp_path / "kitti", "--out", out, "--set", "count=200")
    assert res.exit_code == 0, res.output
    source = open_dataset("kitti", tmp_path / "kitti")
    original = source.load(source.pairs()[0])
    assert not original.flow_valid.all()
    ds = open_dataset("sintel", out, split="training", pass_="snow_clean")
    back = ds.load(ds.pairs()[0])
    assert back.id.scene == "000004_0010"
    assert bool((back.flow_valid == original.flow_valid).all())
    np.testing.assert_allclose(back.flow[original.flow_valid.expand(2, -1, -1)].numpy(),
                               original.flow[original.flow_valid.expand(2, -1, -1)].numpy())
    # and in KITTI's own format, as KITTI tools read it
    from weathergen.io.kitti_formats import read_flow_png

    native, native_valid = read_flow_png(out / "training/flow_occ/000004_0010/frame_0010.png")
    np.testing.assert_array_equal(native_valid, original.flow_valid[0].numpy())
    np.testing.assert_allclose(native[native_valid], original.flow.permute(1, 2, 0).numpy()[native_valid],
                               atol=1 / 64)


def test_full_disk_stops_the_run_with_one_line(tmp_path, monkeypatch):
    import errno

    import weathergen.outputs.formats.png as png_format
    import weathergen.outputs.pairs as outputs

    def no_space(path, *args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(png_format, "write_png", no_space)    # the weather frames
    monkeypatch.setattr(outputs, "write_png", no_space)       # the masks beside them
    out = tmp_path / "full"
    res = run("render", "--out", out, *FAST)
    assert res.exit_code == 2, res.output
    assert "cannot write (No space left on device)" in res.output and "--resume" in res.output
    assert "Traceback" not in res.output
    assert not list(out.rglob("*.png")) and not list(out.rglob("*.npz"))


@pytest.mark.parametrize("content,message", [
    ("text", "not a .npz archive"),
    ({"a": np.zeros(3)}, "no metadata_version"),
    ({"metadata_version": np.array(1, np.int32), "position": np.zeros((2, 3))},
     "incomplete particle-metadata file: no pair_dataset"),
], ids=["not-npz", "foreign-npz", "incomplete"])
def test_inspect_rejects_foreign_files_in_one_line(tmp_path, content, message):
    path = tmp_path / "meta.npz"
    if isinstance(content, str):
        path.write_text(content)
    else:
        np.savez(path, **content)
    res = run("inspect", path)
    assert res.exit_code == 2
    assert res.output.strip() == f"Error: {path}: {message}" or message in res.output.splitlines()[0]
    assert "Traceback" not in res.output and len(res.output.strip().splitlines()) == 1


def test_preview_of_an_exr_only_render_shows_the_weather(tmp_path):
    out = tmp_path / "exr"
    res = run("render", "--out", out, "--format", "exr", *FAST[:2], "--frames-per-scene", "1",
              "--set", "count=300")
    assert res.exit_code == 0, res.output
    res = run("preview", out, "--width", "128")
    assert res.exit_code == 0, res.output
    sheet = read_image(out / "preview.png")
    original, weather = sheet[30:, :128], sheet[30:, 128:256]     # below the captions
    assert (weather - original).max() > 0.2 and (weather - original).mean() > 0.001, \
        "the middle tile must show the snowy frame"


def test_preview_refuses_a_folder_that_is_not_a_render(tmp_path):
    (tmp_path / "photos").mkdir()
    res = run("preview", tmp_path / "photos")
    assert res.exit_code == 2 and "preview takes the folder of a render output" in res.output
    (tmp_path / "photos" / "manifest.json").write_text("[1, 2]")
    res = run("preview", tmp_path / "photos")
    assert res.exit_code == 2 and "not a weathergen render manifest" in res.output
    assert "Traceback" not in res.output


def test_world_up_is_a_dataset_setting_recorded_in_the_manifest(snow_run, tmp_path):
    """Snow falls against the world's up axis: -z on the z-up demo world, +z if told the world is upside down."""
    down = stored_values(read_metadata(snow_run / "training/particles/street_0001/frame_0001.npz"),
                         "motion")
    assert (down[:, 2] < 0).all() and np.abs(down[:, :2]).max() < 1e-6
    assert json.loads((snow_run / "manifest.json").read_text())["input"]["world_up"] == "+z"
    out = tmp_path / "flipped"
    res = run("render", "--out", out, "--world-up", "-z", *FAST)
    assert res.exit_code == 0, res.output
    up = stored_values(read_metadata(out / "training/particles/street_0001/frame_0001.npz"),
                       "motion")
    assert (up[:, 2] > 0).all()
    res = run("render", "--out", tmp_path / "bad", "--world-up", "up", *FAST)
    assert res.exit_code == 2 and "--world-up" in res.output
    # a direction (a world that is not level), here nearly -z, written with a leading minus
    res = run("render", "--out", tmp_path / "vector", "--world-up", "-0.001,0,-1", *FAST)
    assert res.exit_code == 0, res.output
    up = stored_values(read_metadata(tmp_path / "vector/training/particles/street_0001/frame_0001.npz"),
                       "motion")
    assert (up[:, 2] > 0).all()
    assert json.loads((tmp_path / "vector/manifest.json").read_text())["input"]["world_up"] == "-0.001,0,-1"


def test_preview_caption_outline_stays_around_the_text():
    # The dark outline must follow the white caption; a thicker stroke advances wider per
    # character and leaves a dark copy of the last letters beside the caption.
    from weathergen.render.preview import caption_tile

    tile = caption_tile(np.full((100, 200, 3), 0.5, np.float32), (200, 100), "courtyard 10")
    band = tile[:30].astype(int).sum(axis=2)
    white_cols = np.nonzero((band > 3 * 200).any(axis=0))[0]
    dark_cols = np.nonzero((band < 3 * 60).any(axis=0))[0]
    assert white_cols.size and dark_cols.size
    assert dark_cols.max() <= white_cols.max() + 2
    assert dark_cols.min() >= white_cols.min() - 2


@pytest.mark.parametrize("args,message", [
    (("--dataset", "kitti"), "KITTI 2015 layout"),
    (("--scenes", "nowhere"), "nowhere"),
])
def test_a_root_or_selection_that_does_not_fit_writes_nothing(tmp_path, demo_root, args, message):
    # The pairs are listed before the output folder is created, so a corrected command can use
    # the same --out (a left-over folder would be refused as "already holds a render").
    out = tmp_path / "o"
    res = run("render", "--root", demo_root, "--out", out, *args)
    assert res.exit_code == 2, res.output
    assert message in res.output
    assert not out.exists()
    res = run("render", "--root", demo_root, "--out", out, *FAST)
    assert res.exit_code == 0, res.output


def test_strong_forward_motion_is_recorded_and_noted_once(tmp_path):
    """A pair whose frame 2 keeps fewer than half of the particles frame 1 shows (the camera
    drives one unit into the sampling box) is marked in the manifest, and the run prints one note
    for all such pairs that names the weather-field presets; a still camera is not marked."""
    from engine_scenes import assert_few_in_frame2_marked, write_motion_scenes

    small = dict(size=(48, 64), focal=56.0, wall_columns=20)
    root = tmp_path / "sintel"
    write_motion_scenes(root, **small)
    out = tmp_path / "out"
    res = run("render", "--root", root, "--out", out, "--set", "count=300", "--set", "scale_count=false",
              "--quiet")
    assert res.exit_code == 0, res.output
    notes = [line for line in res.output.splitlines() if "frame 2" in line]
    assert len(notes) == 1, res.output
    assert notes[0].startswith("Note: in 2 pairs") and "snow-moderate" in notes[0]
    assert_few_in_frame2_marked(out)

    # a field preset fills the world both cameras see: nothing to note
    res = run("render", "--root", root, "--out", tmp_path / "field", "--preset", "snow-light",
              "--quiet")
    assert res.exit_code == 0 and "frame 2" not in res.output, res.output


@pytest.mark.cuda
def test_render_on_cuda_writes_what_the_cpu_writes(snow_run, tmp_path):
    """`render --device cuda` (batches of 8 by default there): the same particles, frames within
    one grey level of the CPU run's."""
    out = tmp_path / "cuda"
    res = run("render", "--out", out, "--device", "cuda", *FAST)
    assert res.exit_code == 0, res.output
    for meta in sorted(snow_run.rglob("particles/*/*.npz")):
        gpu, cpu = read_metadata(out / meta.relative_to(snow_run)), read_metadata(meta)
        for key in ("position", "motion", "color", "transparency", "scale"):
            np.testing.assert_array_equal(gpu[key], cpu[key], err_msg=key)
    frames = sorted(p.relative_to(snow_run) for p in snow_run.rglob("snow_clean/*/*.png"))
    assert frames
    for rel in frames:
        diff = np.abs(read_image(out / rel) - read_image(snow_run / rel))
        assert diff.max() <= 1 / 255 + 1e-6, rel
