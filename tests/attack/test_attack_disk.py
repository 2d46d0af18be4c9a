"""`weathergen attack` on a disk that refuses a write (full, or a sub-folder it cannot create) ends
as `render` does: exit 2, one line naming the file and what to do, no file half-written, and
`--resume` finishes the run."""

from __future__ import annotations

import errno
import json

import pytest
from click.testing import CliRunner

pytestmark = pytest.mark.slow


def invoke(args):
    from weathergen.cli.main import _register, cli

    _register()
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


@pytest.mark.parametrize("how", ["full", "blocked"])
def test_a_refused_write_is_one_line_and_resume_finishes(how, tmp_path, monkeypatch,
                                                         raft_small_weights):
    import weathergen.outputs.attack as attack_outputs

    real = attack_outputs.write_flo
    out = tmp_path / "two"
    blocker = out / "training" / "attack_flow" / "street_0001"

    def refusing(path, flow):
        if "street_0001" not in str(path):
            return real(path, flow)
        if how == "full":                   # the disk fills up while the second pair is written
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        blocker.parent.mkdir(parents=True, exist_ok=True)
        blocker.write_text("")              # a file where the pair's folder must go
        return real(path, flow)

    args = ["attack", "--model", "raft-small", "--checkpoint", raft_small_weights, "--iters", "1",
            "--scenes", "courtyard,street", "--frames-per-scene", "1", "--steps", "1",
            "--set", "count=40", "--out", out, "--quiet"]
    monkeypatch.setattr(attack_outputs, "write_flo", refusing)
    refused = invoke(args)
    assert refused.exit_code == 2, refused.output
    (line,) = [x for x in refused.output.strip().splitlines() if x.startswith("Error")]
    assert "street_0001" in line and "cannot write" in line and "--resume" in line
    assert "Traceback" not in refused.output
    if how == "full":
        assert "No space left on device" in line and "free some space" in line
    assert not list(out.rglob(".*.tmp*"))                       # nothing half-written
    assert not (out / "training" / "particles" / "street_0001").exists()
    manifest = json.loads((out / "manifest.json").read_text())
    assert [e["pair"] for e in manifest["pairs"].values()] == ["demo/training/courtyard/0001"]

    monkeypatch.setattr(attack_outputs, "write_flo", real)
    if blocker.is_file():
        blocker.unlink()
    resumed = invoke([*args, "--resume"])
    assert resumed.exit_code == 0, resumed.output
    manifest = json.loads((out / "manifest.json").read_text())
    assert sorted(e["pair"] for e in manifest["pairs"].values()) == [
        "demo/training/courtyard/0001", "demo/training/street/0001"]
    assert manifest["summary"]["pairs"] == 2
