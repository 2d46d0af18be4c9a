"""Output folders: the one owner of what a render or attack writes and of reading it back.

- :mod:`.pairs`: where one pair's files go (:class:`PairOutput`) and their writer;
- :mod:`.formats`: the formats of the weather frames (PNG, EXR), one module each, the only
  writer and reader of frame files;
- :mod:`.metadata`: the particle-metadata ``.npz`` of a pair;
- :mod:`.attack`: the extra files of an attacked pair (flows, log, summary);
- :mod:`.manifest`: ``manifest.json`` and ``summary.json`` (write, merge shard parts, read back
  and check, for every reader);
- :mod:`.folder`: claiming a folder for a run (:func:`claim_folder`: lock, markers, resume and
  overwrite rules, temporary files, undo);
- :mod:`.reading`: a finished output read back (weather frames, stored particles).
"""

from __future__ import annotations

from .attack import (FLOW_KINDS, AttackPairOutput, encode_log, read_log, read_pair_summary,
                     write_attack_pair)
from .folder import (ATTACK_FOLDER, RENDER_FOLDER, Claim, FolderKind, claim_folder, folder_size,
                     lock_file, prepare_folder)
from .manifest import (MANIFEST, MANIFEST_PARTS, SUMMARY, OutputManifest, jsonable, merge_manifest,
                       read_attack_manifest, read_manifest, read_run_config, read_summary,
                       shard_part, write_attack_manifest, write_manifest_part, write_run_config)
from .metadata import (FRAME_SCALING, METADATA_KEYS, METADATA_VERSION, identity_arrays,
                       pair_identity, pair_metadata, read_metadata, stored_frame_scaling,
                       write_metadata)
from .pairs import (FORMATS, NATIVE_FLOW, SINTEL_SPLIT_FOLDER, PairOutput, RightView,  # noqa: F401
                    write_pair_outputs)
from .published import PublishedWeatherSet
from .reading import WeatherFolder, load_pair_particles

__all__ = ["PublishedWeatherSet",
           "ATTACK_FOLDER", "AttackPairOutput", "Claim", "FLOW_KINDS", "FORMATS", "FRAME_SCALING",
           "FolderKind",
           "MANIFEST", "MANIFEST_PARTS", "METADATA_KEYS", "METADATA_VERSION", "NATIVE_FLOW",
           "OutputManifest", "RENDER_FOLDER", "RightView", "SINTEL_SPLIT_FOLDER", "SUMMARY", "WeatherFolder",
           "claim_folder", "encode_log", "folder_size", "identity_arrays", "jsonable",
           "load_pair_particles", "lock_file", "merge_manifest", "pair_identity", "pair_metadata",
           "prepare_folder", "read_attack_manifest", "read_log", "read_manifest", "read_metadata",
           "read_pair_summary", "read_run_config", "read_summary", "shard_part", "stored_frame_scaling",
           "write_attack_manifest", "write_attack_pair", "write_manifest_part", "write_metadata",
           "write_pair_outputs", "write_run_config"]
