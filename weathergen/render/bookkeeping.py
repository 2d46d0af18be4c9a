"""What a render run keeps on disk besides its pairs' frames: which files each pair has (for
resumption, and to clean up after a killed run or worker) and the manifest that records the run.

``job`` is a :class:`~weathergen.render.job.RenderJob` throughout, ``results`` its
:class:`~weathergen.render.job.PairResult` objects."""

from __future__ import annotations

import contextlib
from dataclasses import asdict
from datetime import datetime, timezone
from pathlib import Path

from ..datasets import PairRef
from ..errors import OutputError
from ..io.atomic import remove_temporaries, write_error
from ..outputs import PairOutput, merge_manifest, write_manifest_part
from ..outputs.manifest import MANIFEST
from ..words import counted

def pair_output(job, ref: PairRef) -> PairOutput:
    """Where the job writes the pair ``ref``."""
    return PairOutput.of(job.out, ref.id, job.pass_name, job.fmt, job.geometry, job.truth,
                         job.sequence, job.dataset.native_flow)


def pair_files(out: PairOutput, job) -> list[Path]:
    """Every file the job may write for one pair (``out``)."""
    native = out.native_flow
    extra = out.right_files() if job.stereo else []
    if job.truth:
        extra += list(out.truth_files().values())
        extra += [p for p in (out.native_truth(kind) for kind in ("particle", "seen"))
                  if p is not None]
    return out.files(with_flow=True) + [out.invalid_mask] + ([native] if native else []) + extra


def temporary_places(job, refs) -> list[tuple[Path, str]]:
    """Where a killed run of this shard may have left temporary files of its pairs (atomic writes
    that never reached their rename), as ``(folder, name prefix)``: the folders of this shard's
    pairs (:func:`~weathergen.outputs.claim_folder` adds the shard's bookkeeping). Other shards may
    be running; their files are left alone."""
    folders = set()
    for ref in refs:
        folders.update(path.parent for path in pair_files(pair_output(job, ref), job))
    return [(folder, ".") for folder in sorted(folders)]


def forget_lost(job, refs) -> None:
    """Undo what the stopped workers wrote of ``refs``, whose results were lost with the pool:
    the temporary files (writes that never reached the rename) and a metadata file (written last:
    a worker killed after writing it, before its result came back, finished the pair unseen), so
    that the disk holds no pair the manifest does not record; the pair is rendered again or
    stays undone for --resume."""
    for ref in refs:
        out = pair_output(job, ref)
        for path in pair_files(out, job):
            remove_temporaries(path, only_of_dead=False)
        with contextlib.suppress(OSError):
            out.metadata.unlink()


def record_run(job, results: list, started: float, seconds: float) -> Path:
    """Record this run's pairs in the shard's manifest part (merging with its earlier runs), and
    under the run the notes about whole scenes that the run printed (``notes``: a gap in a scene's
    frame numbering)."""
    i, n = job.shard
    counts = {s: sum(r.status == s for r in results) for s in ("written", "skipped", "failed")}
    notes = job.dataset.scene_notes()          # e.g. a gap in a scene's frame numbering
    run = {
        "shard": f"{i}/{n}", "command": job.command, "workers": job.workers, "device": job.device,
        "started": datetime.fromtimestamp(started, timezone.utc).isoformat(timespec="seconds"),
        "seconds": round(seconds, 3), **counts, **({"notes": notes} if notes else {}),
    }
    pairs = {}
    for r in results:
        entry = asdict(r)
        pairs[entry.pop("key")] = entry
    return write_manifest_part(job.out, job.shard, run, pairs)


def record_manifest(job, results, started: float, seconds: float, stopped_by) -> None:
    """Write the manifest; when the disk refuses, say so without hiding why the run stopped."""
    try:
        record_run(job, results, started, seconds)
        merge_manifest(job.out)
    except OSError as exc:
        done = sum(r.status == "written" for r in results)
        note = (f"the manifest could not be updated either ({exc.strerror or exc}); ${{resume}} "
                f"finds the {counted(done, 'pair')} finished in this run on disk")
        if isinstance(stopped_by, OutputError):
            raise OutputError(f"{stopped_by.args[0]}; {note}") from None
        if stopped_by is not None:
            return                  # an interruption or a bug: let it through as it is
        raise write_error(exc, job.out / MANIFEST, "then rerun with ${resume}") from None
