"""Checkpoint files: where named checkpoints live, how to fetch them, and strict loading.

A named checkpoint (``raft-sintel``, ``raft-small``, ...) is a :class:`CheckpointSpec`: plain data
saying which architecture it fits, which file name it has in the user cache, and where its
authors publish it. The cache folder is ``$WEATHERGEN_CACHE/models`` when that variable is set,
else ``$XDG_CACHE_HOME/weathergen/models``, else ``~/.cache/weathergen/models``. A name is looked
up in the cache first, then among the weights shipped with the package (``weights/`` beside this
module: the released RAFT-small, BSD-3, with its licence), so ``raft-small`` works from any
install without a download.

Nothing is downloaded unless asked for (``download=True``, ``--download`` on the command line);
without the file and without permission to fetch it the error says which file to put where.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
import urllib.error
import urllib.request
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Mapping, Optional, Sequence

import torch
from torch import nn

from ..errors import ConfigError, FormatError

#: How many names an error message lists before it says "... and N more".
_LIST_LIMIT = 8


@dataclass(frozen=True)
class CheckpointSpec:
    """A published checkpoint, described as data.

    Attributes:
        name: the name users type (``raft-sintel``); also the cached file's stem.
        architecture: the registered model it fits (``raft``).
        description: one line on what it was trained on.
        url: an archive (zip) that contains the file, the file itself when ``member`` is
            ``None``, or ``None`` when it cannot be downloaded automatically.
        member: the file's path inside that archive (or its name on ``page``).
        sha256: the file's checksum where known; a downloaded file that differs is rejected.
        page: where the authors publish the file for manual download when there is no ``url``
            (a shared folder, for instance).
        parts: for weights published as several files (one per pyramid level, say): their
            names, each fetched from ``url`` + name; ``pack`` turns the downloaded files (in
            this order) into one state dict, which is saved as the cached file.
        pack: see ``parts``.
        part_sha256: ``(name, sha256)`` of the parts whose checksums are known; a downloaded
            part that differs is rejected.
        licence: the terms of the weights, in a few words (for listings and messages).
    """

    name: str
    architecture: str
    description: str
    url: Optional[str] = None
    member: Optional[str] = None
    sha256: Optional[str] = None
    page: Optional[str] = None
    parts: tuple[str, ...] = ()
    pack: Optional[Callable[[Sequence[Path]], dict]] = None
    part_sha256: tuple[tuple[str, str], ...] = ()
    licence: Optional[str] = None

    @property
    def filename(self) -> str:
        return f"{self.name}.pth"


def cache_dir() -> Path:
    """The folder where named checkpoints are looked up and downloaded to."""
    root = os.environ.get("WEATHERGEN_CACHE")
    if root:
        return Path(root).expanduser() / "models"
    xdg = os.environ.get("XDG_CACHE_HOME")
    base = Path(xdg).expanduser() if xdg else Path.home() / ".cache"
    return base / "weathergen" / "models"


#: Released weights shipped inside the package (with their licences), found by name.
SHIPPED_DIR = Path(__file__).resolve().parent / "weights"


def shipped_path(spec: CheckpointSpec) -> Optional[Path]:
    """The file of ``spec`` shipped with the package (``SHIPPED_DIR``), or None."""
    path = SHIPPED_DIR / spec.filename
    return path if path.is_file() else None


def cached_path(spec: CheckpointSpec) -> Path:
    """Where the file of a named checkpoint is (or would be) in the cache."""
    return cache_dir() / spec.filename


def resolve_named(spec: CheckpointSpec, download: bool = False, timeout: float = 60.0) -> Path:
    """The file of ``spec``: the cached one, else the one shipped with the package, else (when
    ``download`` is true) fetched into the cache.

    Raises:
        ConfigError: the file is missing and may not (or cannot) be downloaded; the message
            says which file to put where.
    """
    path = cached_path(spec)
    if path.is_file():
        return path
    shipped = shipped_path(spec)
    if shipped is not None:
        return shipped
    if download and spec.url:
        return download_checkpoint(spec, timeout=timeout)
    source = _origin(spec)
    hint = " or let weathergen fetch it (--download; download=True in Python)" if spec.url and not download else ""
    raise ConfigError(f"checkpoint {spec.name!r} is not in the cache: put {spec.filename}"
                      f"{source} at {path}{hint}, or give the checkpoint as a file path")


def _origin(spec: CheckpointSpec) -> str:
    """`` (it is X in URL)``: where the file comes from, for messages; empty if unknown."""
    if spec.url and spec.parts:
        return (f" (packed from {spec.parts[0]} ... {spec.parts[-1]} at {spec.url}, or give "
                f"those files as the checkpoint)")
    if spec.url and spec.member:
        return f" (it is {spec.member} in {spec.url})"
    if spec.url:
        return f" (from {spec.url})"
    if spec.page:
        return f" (it is {spec.member} at {spec.page})" if spec.member else f" (from {spec.page})"
    return ""


def download_checkpoint(spec: CheckpointSpec, timeout: float = 60.0) -> Path:
    """Fetch the archive of ``spec``, extract its file into the cache, return the file's path.

    The archive is written to a temporary file beside the cache and the checkpoint is moved into
    place only when complete (and its checksum matches, where known), so an interrupted download
    never leaves a truncated checkpoint behind.

    Raises:
        ConfigError: no URL, no network, a timeout, or an archive without the expected file.
    """
    if not spec.url:
        raise ConfigError(f"checkpoint {spec.name!r} has no download address; put "
                          f"{spec.filename}{_origin(spec)} at {cached_path(spec)}")
    target = cached_path(spec)
    target.parent.mkdir(parents=True, exist_ok=True)
    if spec.parts:
        return _download_parts(spec, target, timeout)
    with tempfile.TemporaryDirectory(dir=target.parent, prefix=".download-") as tmp:
        archive = Path(tmp) / ("archive.zip" if spec.member else spec.filename)
        try:
            with urllib.request.urlopen(spec.url, timeout=timeout) as response, \
                    open(archive, "wb") as out:
                shutil.copyfileobj(response, out, length=1 << 20)
        except (urllib.error.URLError, OSError) as exc:  # includes timeouts
            raise ConfigError(f"could not download {spec.url} ({exc}); put {spec.filename}"
                              f"{_origin(spec)} at {target}") from exc
        extracted = Path(tmp) / spec.filename
        if spec.member:  # an archive: take the one file out
            try:
                with zipfile.ZipFile(archive) as zf, zf.open(spec.member) as src, \
                        open(extracted, "wb") as dst:
                    shutil.copyfileobj(src, dst, length=1 << 20)
            except (zipfile.BadZipFile, KeyError) as exc:
                raise ConfigError(f"the archive at {spec.url} does not hold {spec.member} "
                                  f"({exc}); put {spec.filename} at {target} by hand") from exc
        if spec.sha256 is not None:
            digest = sha256_of(extracted)
            if digest != spec.sha256:
                raise ConfigError(f"downloaded {spec.member} has sha256 {digest}, expected "
                                  f"{spec.sha256}; put a verified {spec.filename} at {target}")
        os.replace(extracted, target)  # atomic within one file system
    return target


def _download_parts(spec: CheckpointSpec, target: Path, timeout: float) -> Path:
    """Fetch every file of ``spec.parts``, pack them into one state dict, save it at ``target``
    (atomically: nothing is left behind when a part is missing or does not read)."""
    with tempfile.TemporaryDirectory(dir=target.parent, prefix=".download-") as tmp:
        paths = []
        for part in spec.parts:
            path = Path(tmp) / part
            url = spec.url + part
            try:
                with urllib.request.urlopen(url, timeout=timeout) as response, \
                        open(path, "wb") as out:
                    shutil.copyfileobj(response, out, length=1 << 20)
            except (urllib.error.URLError, OSError) as exc:  # includes timeouts
                raise ConfigError(f"could not download {url} ({exc}); put {spec.filename}"
                                  f"{_origin(spec)} at {target}") from exc
            expected = dict(spec.part_sha256).get(part)
            if expected is not None and sha256_of(path) != expected:
                raise ConfigError(f"downloaded {url} has sha256 {sha256_of(path)}, expected "
                                  f"{expected}; put {spec.filename}{_origin(spec)} at {target}")
            paths.append(path)
        packed = Path(tmp) / spec.filename
        torch.save(spec.pack(paths), packed)
        os.replace(packed, target)
    return target


def sha256_of(path: Path) -> str:
    """Hex sha256 of a file, read in chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def read_state_dict(path: str | Path) -> dict[str, torch.Tensor]:
    """Read a checkpoint file that holds a ``state_dict`` (name -> tensor) onto the CPU.

    A file that holds a dictionary with a ``state_dict`` entry (a training checkpoint with
    the epoch and other records beside the weights) gives that entry.

    Only tensors and plain containers are unpickled (``weights_only=True``).

    Raises:
        ConfigError: the file does not exist.
        FormatError: the file cannot be read, or holds something other than a state dict.
    """
    path = Path(path)
    if path.is_dir():
        raise FormatError(path, "is a folder; expected a checkpoint file")
    if not path.is_file():
        raise ConfigError(f"checkpoint file {path} does not exist")
    _check_checkpoint_header(path)
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for corrupt files; all mean the same here
        text = str(exc).strip()
        if "Weights only load failed" in text:
            reason = "it holds objects other than tensors, or is damaged"
        elif isinstance(exc, KeyError) or not text:
            reason = f"damaged or not a checkpoint: {type(exc).__name__}"
        else:
            reason = text.splitlines()[0]
        raise FormatError(path, f"cannot be read as a PyTorch checkpoint ({reason})") from exc
    if isinstance(obj, Mapping) and isinstance(obj.get("state_dict"), Mapping):
        # A training checkpoint ({"epoch": ..., "state_dict": ..., ...}), as FlowNet2's files.
        obj = obj["state_dict"]
    if not isinstance(obj, Mapping) or not obj:
        raise FormatError(path, f"expected a state dict (parameter name -> tensor), "
                                f"got {type(obj).__name__}")
    bad = [k for k, v in obj.items() if not isinstance(k, str) or not isinstance(v, torch.Tensor)]
    if bad:
        raise FormatError(path, f"expected a state dict (parameter name -> tensor); entries "
                                f"that are not tensors: {_short_list(map(str, bad))}")
    return dict(obj)


def read_tensor_file(path: str | Path) -> torch.Tensor:
    """Read a file that holds one tensor (saved with ``torch.save(tensor, path)``), on the CPU.

    Raises:
        ConfigError: the file does not exist.
        FormatError: the file cannot be read, or holds something other than one tensor.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"weight file {path} does not exist")
    _check_checkpoint_header(path)
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # as in read_state_dict: every failure means a bad file
        text = str(exc).strip().splitlines()
        raise FormatError(path, f"cannot be read as a PyTorch file "
                                f"({text[0] if text else type(exc).__name__})") from exc
    if not isinstance(obj, torch.Tensor):
        raise FormatError(path, f"expected one tensor, got {type(obj).__name__}")
    return obj


def _check_checkpoint_header(path: Path) -> None:
    """Refuse files that are neither of torch's formats (a zip archive, or a pickle stream).

    Without this, ``torch.load`` of a text file fails with a bare ``KeyError`` of a byte value.
    """
    try:
        with open(path, "rb") as f:
            head = f.read(64)
    except OSError as exc:
        raise FormatError(path, f"cannot read checkpoint file ({exc.strerror or exc})") from None
    if not head:
        raise FormatError(path, "is empty, not a PyTorch checkpoint")
    if head.startswith(b"PK\x03\x04") or (len(head) > 1 and head[0] == 0x80 and 2 <= head[1] <= 5):
        return
    try:
        first_line = head.decode("ascii").strip().splitlines()[0][:24]
        kind = f"a text file (it starts with {first_line!r})"
    except (UnicodeDecodeError, IndexError):
        kind = "neither a zip archive nor a pickle stream"
    raise FormatError(path, f"not a PyTorch checkpoint: {kind}; expected a .pth/.pt file saved "
                            f"with torch.save")


def strip_prefix(state_dict: Mapping[str, torch.Tensor], prefix: str) -> dict[str, torch.Tensor]:
    """Remove ``prefix`` from every key when every key has it (``module.`` of DataParallel)."""
    if state_dict and all(k.startswith(prefix) for k in state_dict):
        return {k[len(prefix):]: v for k, v in state_dict.items()}
    return dict(state_dict)


def load_strict(module: nn.Module, state_dict: Mapping[str, torch.Tensor], source: str | Path,
                what: str, optional_suffixes: tuple[str, ...] = ("num_batches_tracked",)) -> None:
    """Copy ``state_dict`` into ``module``, requiring the same names and shapes.

    Keys ending in one of ``optional_suffixes`` may be missing from the file (batch-norm step
    counters: they do not affect a model in evaluation mode).

    Raises:
        FormatError: naming ``source`` and listing missing keys, unexpected keys and shape
            mismatches (each list shortened).
    """
    expected = module.state_dict()
    missing = [k for k in expected if k not in state_dict and not k.endswith(optional_suffixes)]
    unexpected = [k for k in state_dict if k not in expected]
    mismatched = [f"{k} (file {tuple(v.shape)}, model {tuple(expected[k].shape)})"
                  for k, v in state_dict.items() if k in expected and v.shape != expected[k].shape]
    problems = []
    if missing:
        problems.append(f"missing keys ({len(missing)}): {_short_list(missing)}")
    if unexpected:
        problems.append(f"unexpected keys ({len(unexpected)}): {_short_list(unexpected)}")
    if mismatched:
        problems.append(f"shape mismatches ({len(mismatched)}): {_short_list(mismatched)}")
    if problems:
        raise FormatError(source, f"does not fit {what}: " + "; ".join(problems))
    module.load_state_dict(state_dict, strict=False)  # names and shapes checked above


def _short_list(items, limit: int = _LIST_LIMIT) -> str:
    items = list(items)
    shown = ", ".join(items[:limit])
    return shown if len(items) <= limit else f"{shown}, ... and {len(items) - limit} more"
