"""Output folders: reading a manifest back, claiming a folder, merging manifest parts, stored particles."""

from __future__ import annotations

import json

import numpy as np
import pytest

from weathergen.cli.options import option_of
from weathergen.engine import empty_particles
from weathergen.errors import ConfigError, FolderBusy, FormatError, NothingRendered
from weathergen.framepair import PairId
from weathergen.io.lock import FolderLock
from weathergen.outputs import (ATTACK_FOLDER, RENDER_FOLDER, PairOutput, claim_folder,
                                load_pair_particles, lock_file, merge_manifest, pair_metadata,
                                prepare_folder, read_manifest, read_run_config, read_summary,
                                write_attack_manifest, write_manifest_part, write_metadata,
                                write_run_config)

RENDER = {"preset_name": "snow", "preset": {"count": 3}, "input": {"dataset": "demo"},
          "outputs": {"pass": "snow_clean", "format": "exr", "geometry": False}}


def test_read_manifest_gives_what_each_reader_needs(tmp_path):
    (tmp_path / "manifest.json").write_text(json.dumps(RENDER))
    m = read_manifest(tmp_path, "preview")
    assert (m.preset_name, m.pass_name, m.fmt, m.geometry) == ("snow", "snow_clean", "exr", False)
    assert m.input == {"dataset": "demo"} and m.folder == tmp_path
    # An evaluate reader needs the pass only; the format defaults to PNG.
    (tmp_path / "manifest.json").write_text(json.dumps({"input": {}, "outputs": {"pass": "p"}}))
    assert read_manifest(tmp_path, "weather").fmt == "png"
    with pytest.raises(FormatError, match="manifest.json: not a weathergen render manifest"):
        read_manifest(tmp_path, "particles_from")


def test_a_folder_without_manifest_names_the_parameter(tmp_path):
    with pytest.raises(ConfigError) as missing:
        read_manifest(tmp_path, "particles_from")
    assert str(missing.value).endswith("not found; particles_from takes the folder of an earlier render")
    assert missing.value.render(option_of).endswith("--particles takes the folder of an earlier render")
    (tmp_path / "manifest.json").write_text("{not json")
    with pytest.raises(FormatError, match="not a weathergen render or attack manifest"):
        read_manifest(tmp_path, "weather")


def test_prepare_folder_claims_new_folders_and_refuses_others(tmp_path):
    config = {"seed": 1}
    out = tmp_path / "run"
    prepare_folder(out, RENDER_FOLDER, config, None, resume=False, overwrite=False)
    assert (out / ".weathergen-render").read_text() == "weathergen render output\n"
    # Not ours: refused, unless overwrite.
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("x")
    with pytest.raises(ConfigError) as foreign:
        prepare_folder(mine, RENDER_FOLDER, config, None, resume=False, overwrite=False)
    assert foreign.value.render(option_of).endswith(
        "was not created by weathergen render (use --overwrite to write into it anyway)")
    with pytest.raises(ConfigError, match="not written by weathergen attack"):
        prepare_folder(mine, ATTACK_FOLDER, config, None, resume=False, overwrite=False)
    prepare_folder(mine, ATTACK_FOLDER, config, None, resume=False, overwrite=True)
    assert (mine / ".weathergen-attack").is_file()
    with pytest.raises(ConfigError, match="exists and is not a folder"):
        prepare_folder(mine / "notes.txt", RENDER_FOLDER, config, None, resume=False,
                       overwrite=True)


def test_a_folder_that_holds_a_run_needs_resume_with_the_same_settings(tmp_path):
    out = tmp_path / "run"
    prepare_folder(out, RENDER_FOLDER, {"seed": 1}, None, resume=False, overwrite=False)
    (out / "x.png").write_bytes(b"")
    previous = {"seed": 1, "preset": "snow"}
    with pytest.raises(ConfigError, match=r"already holds a render \(use resume to finish it"):
        prepare_folder(out, RENDER_FOLDER, previous, previous, resume=False, overwrite=False)
    stale = out / "training" / ".frame.png.tmp123"
    stale.parent.mkdir()
    stale.write_bytes(b"half")
    prepare_folder(out, RENDER_FOLDER, previous, previous, resume=True, overwrite=False)
    assert not stale.exists()                       # a killed run's temporary file is gone
    prepare_folder(out, RENDER_FOLDER, previous, previous, resume=False, overwrite=False,
                   shared=True)                     # another shard of the same run
    with pytest.raises(ConfigError, match=r"was rendered with different settings \(preset, seed\)"):
        prepare_folder(out, RENDER_FOLDER, {"seed": 2, "preset": "rain"}, previous, resume=True,
                       overwrite=False)
    prepare_folder(out, RENDER_FOLDER, {"seed": 2}, previous, resume=False, overwrite=True)


def test_resume_and_overwrite_remove_a_killed_runs_temporaries_exr_ones_too(tmp_path):
    out = tmp_path / "run"
    prepare_folder(out, RENDER_FOLDER, {"seed": 1}, None, resume=False, overwrite=False)
    pair = out / "training" / "snow_clean" / "alley_0001"
    pair.mkdir(parents=True)
    for mode in ("resume", "overwrite"):
        left = [pair / ".frame_0001.png.4242.abcd1234.tmp",
                pair / ".frame_0001.exr.4242.efgh5678.tmp.exr"]
        kept = pair / "frame_0001.png"
        for f in (*left, kept):
            f.write_bytes(b"x")
        prepare_folder(out, RENDER_FOLDER, {"seed": 1}, {"seed": 1}, resume=mode == "resume",
                       overwrite=mode == "overwrite", temporary=[(pair, ".")])
        assert not any(f.exists() for f in left) and kept.exists(), mode


def test_a_run_killed_before_it_recorded_anything_leaves_temporaries_the_next_removes(tmp_path):
    """An attack folder's record is its manifest, written after the first pair: a run killed
    during it leaves the marker and a temporary file, and the next run (no --resume needed,
    there is nothing to resume) removes the temporary; a real file stays."""
    out = tmp_path / "attack"
    prepare_folder(out, ATTACK_FOLDER, {"seed": 1}, None, resume=False, overwrite=False)
    left = out / "alley_0001" / ".frame_0001.png.4242.abcd1234.tmp"
    kept = out / "alley_0001" / "frame_0001.png"
    left.parent.mkdir()
    for f in (left, kept):
        f.write_bytes(b"x")
    prepare_folder(out, ATTACK_FOLDER, {"seed": 1}, None, resume=False, overwrite=False)
    assert not left.exists() and kept.exists()


def test_claim_folder_holds_the_folder_for_its_block_and_leaves_no_lock(tmp_path):
    out, config = tmp_path / "run", {"seed": 1}
    with claim_folder(out, RENDER_FOLDER, config, resume=False, overwrite=False) as claim:
        assert claim.created and claim.previous is None and claim.stale is None
        assert (out / RENDER_FOLDER.marker).is_file() and read_run_config(out) == config
        with pytest.raises(FolderBusy):             # one run at a time
            with claim_folder(out, RENDER_FOLDER, config, resume=True, overwrite=False):
                pass
        (out / "x.png").write_bytes(b"")
    assert not (out / lock_file()).exists()
    with pytest.raises(ConfigError, match="already holds a render"):
        with claim_folder(out, RENDER_FOLDER, config, resume=False, overwrite=False):
            pass
    stale = out / ".x.png.tmp1"
    stale.write_bytes(b"half")
    with claim_folder(out, RENDER_FOLDER, config, resume=True, overwrite=False) as again:
        assert not again.created and again.previous == config
    assert not stale.exists()                       # a killed run's temporary file is gone


def test_claim_folder_undoes_a_folder_it_created_when_nothing_was_rendered(tmp_path):
    out = tmp_path / "new"
    with pytest.raises(NothingRendered):
        with claim_folder(out, RENDER_FOLDER, {}, resume=False, overwrite=False, shard=(1, 2)):
            write_manifest_part(out, (1, 2), {}, {"a": {"status": "failed"}})
            merge_manifest(out)
            raise NothingRendered("every selected pair failed")
    assert not out.exists()
    # a folder that was there before stays, with its record
    kept = tmp_path / "kept"
    kept.mkdir()
    with pytest.raises(NothingRendered):
        with claim_folder(kept, RENDER_FOLDER, {}, resume=False, overwrite=False):
            raise NothingRendered("every selected pair failed")
    assert (kept / RENDER_FOLDER.marker).is_file() and not (kept / lock_file()).exists()


def test_claim_folder_gives_an_attack_its_earlier_manifest_and_notes_a_stale_lock(tmp_path):
    import subprocess
    import sys

    out, config = tmp_path / "attack", {"preset_name": "snow", "preset": {}, "seed": 0,
                                        "input": {}, "outputs": {"pass": "p"}}
    with claim_folder(out, ATTACK_FOLDER, config, resume=False, overwrite=False):
        write_attack_manifest(out, config, {"k": {"status": "written"}}, {"pairs": 1}, [{"run": 1}])
    assert read_summary(out) == {"pairs": 1} and read_summary(tmp_path) is None
    # a killed holder's record stays in the lock file
    code = (f"from weathergen.io.lock import FolderLock; FolderLock({str(out / lock_file())!r})"
            ".acquire(); import os; os._exit(0)")
    dead = subprocess.Popen([sys.executable, "-c", code])
    assert dead.wait() == 0 and (out / lock_file()).is_file()
    notes = []
    with claim_folder(out, ATTACK_FOLDER, config, resume=True, overwrite=False,
                      on_note=notes.append) as claim:
        assert claim.previous["pairs"] == {"k": {"status": "written"}}
        assert claim.previous["runs"] == [{"run": 1}]
    assert len(notes) == 1 and f"took over the stale lock of pid {dead.pid} on" in notes[0]
    with pytest.raises(ConfigError, match=r"attacked with different settings \(seed\)"):
        with claim_folder(out, ATTACK_FOLDER, {**config, "seed": 1}, resume=True, overwrite=False):
            pass
    with FolderLock(out / lock_file()):              # the lock another run holds
        with pytest.raises(FolderBusy):
            with claim_folder(out, ATTACK_FOLDER, config, resume=True, overwrite=False):
                pass


def test_manifest_parts_merge_and_skipped_pairs_keep_their_entry(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    write_run_config(out, {"seed": 4, "preset_name": "snow"})
    written = {"status": "written", "seconds": 2.0}
    write_manifest_part(out, (1, 2), {"shard": "1/2"}, {"a": written, "b": {"status": "failed"}})
    write_manifest_part(out, (1, 2), {"shard": "1/2"}, {"a": {"status": "skipped", "seconds": 0}})
    write_manifest_part(out, (2, 2), {"shard": "2/2"}, {"c": written})
    manifest = json.loads(merge_manifest(out).read_text())
    assert manifest["seed"] == 4 and manifest["format"] == "weathergen-render"
    assert list(manifest["pairs"]) == ["a", "b", "c"] and manifest["pairs"]["a"] == written
    assert manifest["summary"] == {"written": 2, "skipped": 0, "failed": 1}
    assert len(manifest["runs"]) == 3 and manifest["shards"] == ["shard-1-of-2", "shard-2-of-2"]
    (out / "manifest.d" / "shard-2-of-2.json").write_text("{")
    with pytest.raises(FormatError, match=r"shard-2-of-2\.json: manifest part is not valid JSON"):
        merge_manifest(out)


def test_stored_particles_load_for_their_own_pair_only(tmp_path):
    pid = PairId("demo", "training", "street", 1)
    meta = pair_metadata(empty_particles(), pid, 7, {"count": 0}, "snow")
    meta["files"] = np.array("[]")
    write_metadata(PairOutput.of(tmp_path, pid, "").metadata, meta)
    assert load_pair_particles(tmp_path, pid).count == 0
    other = PairId("demo", "training", "street", 2)
    with pytest.raises(FormatError, match="no particle metadata for pair"):
        load_pair_particles(tmp_path, other)
    path = PairOutput.of(tmp_path, other, "").metadata
    write_metadata(path, meta)                      # the first pair's metadata, in the wrong place
    with pytest.raises(FormatError, match="metadata belongs to street frame 1, not to street frame 2"):
        load_pair_particles(tmp_path, other)


def test_a_pair_lists_its_files_and_is_complete_when_they_exist(tmp_path):
    """The metadata's list of written files, read in one place (completion, sequence videos)."""
    pid = PairId("demo", "training", "street", 1)
    out = PairOutput.of(tmp_path, pid, "snow_clean")
    with pytest.raises(FormatError):
        out.listed_files()
    assert not out.is_complete()
    meta = pair_metadata(empty_particles(), pid, 7, {"count": 0}, "snow")
    meta["files"] = np.array(json.dumps([str(p.relative_to(tmp_path)) for p in out.frame_files("png")]))
    write_metadata(out.metadata, meta)
    assert out.listed_files() == list(out.frame_files("png"))
    assert not out.is_complete()
    for p in out.frame_files("png"):
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(b"")
    assert out.is_complete()
