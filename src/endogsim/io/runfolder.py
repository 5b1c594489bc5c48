"""Run folders: one command at a time, a record of what they were made from, no leftovers after a failure.

A *run folder* is the ``--out`` of a command that writes one (``reconstruct``, ``identify``, ``run``,
``simulate``, ``synth``).

- :func:`run_folder` wraps a command's work on one: it refuses a path that names a file, creates the
  folder (and its missing parents), holds an exclusive lock on it for the duration, checks that it is
  writable, and, when the command fails, removes the folders it created if they are still empty.
- The lock is an OS file lock (``flock``) on a sibling file ``.<name>.lock`` that holds the holder's PID
  and command; a second command on the same folder is refused with that PID. The OS releases the lock
  when the holder exits, however it exits: the file a killed run leaves behind locks nothing.
- :func:`provenance` records what a run folder is made from (``provenance.json``) and
  :func:`check_provenance` refuses to continue it with other frames.
- :func:`frames_digest` and :func:`tree_digest` are content hashes for provenance records and for
  checking that a stage's inputs and outputs are still the ones it recorded.
- :func:`load_torch_file` and :func:`check_npz` read a resumable state or say, in one line, that the
  file is corrupt and how to start over.

    with run_folder(out, "reconstruct"):
        ...  # a second `endogsim reconstruct ... --out out` is refused meanwhile
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from endogsim.errors import DataError

try:  # POSIX; elsewhere run folders are not locked
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None  # type: ignore[assignment]

__all__ = ["run_folder", "lock_path", "PROVENANCE", "provenance", "check_provenance", "frames_digest", "tree_digest",
           "json_digest", "load_torch_file", "check_npz"]

#: Locks this process holds: resolved folder -> nesting depth (a command may re-enter its own folder).
_held: dict[str, int] = {}


def lock_path(folder: str | os.PathLike) -> Path:
    """The lock file of a run folder: ``.<name>.lock`` beside it (inside it, a folder that is replaced
    atomically would lose its lock)."""
    folder = Path(folder).resolve()
    return folder.parent / f".{folder.name}.lock"


def _holder(fd: int) -> str:
    """Who holds a lock, from its file: "PID 123 (endogsim identify, since 12:00:03)"."""
    try:
        info = json.loads(os.pread(fd, 4096, 0).decode() or "{}")
    except (OSError, ValueError):
        info = {}
    if "pid" not in info:
        return "another process"
    return f"PID {info['pid']} (endogsim {info.get('command', '?')}, since {info.get('since', '?')})"


@contextmanager
def _exclusive(folder: Path, command: str) -> Iterator[None]:
    """Hold the lock of ``folder`` (re-entrant within this process); DataError naming the holder if taken."""
    key = str(folder.resolve())
    if key in _held or fcntl is None:
        _held[key] = _held.get(key, 0) + 1
        try:
            yield
        finally:
            _held[key] -= 1
            if not _held[key]:
                del _held[key]
        return
    lock = lock_path(folder)
    while True:
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise DataError(f"{folder}: cannot write in {lock.parent} ({exc.strerror}); choose another --out") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            holder = _holder(fd)
            os.close(fd)
            raise DataError(f"{folder} is in use by {holder}; wait for it to finish or choose another "
                            "output folder") from None
        # The previous holder removes the file when it is done; if it did so between our open and our
        # lock, we hold a lock on a file nobody else can see: start again.
        try:
            if os.stat(lock).st_ino == os.fstat(fd).st_ino:
                break
        except FileNotFoundError:
            pass
        os.close(fd)
    os.ftruncate(fd, 0)
    os.pwrite(fd, json.dumps({"pid": os.getpid(), "command": command,
                              "since": time.strftime("%Y-%m-%d %H:%M:%S")}).encode(), 0)
    _held[key] = 1
    try:
        yield
    finally:
        del _held[key]
        try:
            os.unlink(lock)
        except FileNotFoundError:
            pass
        os.close(fd)


@contextmanager
def run_folder(path: str | os.PathLike, command: str) -> Iterator[Path]:
    """Work on the run folder ``path`` as ``command``: created, locked and checked writable for the block.

    Raises DataError when ``path`` names a file, cannot be created or written, or is locked by another
    command. If the block raises, the folders this call created are removed again when they are empty.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise DataError(f"{path} is a file; the output must be a folder (choose another --out)")
    created = []  # deepest first
    p = path.absolute()
    while not p.exists() and p != p.parent:
        created.append(p)
        p = p.parent
    done = False
    try:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise DataError(f"{path.parent}: cannot create the folder ({exc.strerror})") from None
        with _exclusive(path, command):
            try:
                path.mkdir(exist_ok=True)
                with tempfile.TemporaryFile(dir=path):
                    pass
            except OSError as exc:
                raise DataError(f"{path}: cannot write here ({exc.strerror}); choose another --out") from None
            yield path
        done = True
    finally:
        if not done:
            for d in created:
                try:
                    d.rmdir()
                except OSError:  # not empty (or already gone): keep it and its parents
                    break


# ------------------------------------------------------------------------------------------------------ digests
def frames_digest(frames: np.ndarray) -> str:
    """SHA-256 (hex) of frames [T, H, W, 3] in [0, 1], quantised to 8 bits, and of their shape."""
    h = hashlib.sha256(str(tuple(frames.shape)).encode())
    for f in frames:  # frame by frame: no 8-bit copy of the whole video
        h.update(np.ascontiguousarray(np.round(np.clip(f, 0, 1) * 255)).astype(np.uint8).tobytes())
    return h.hexdigest()


def tree_digest(path: str | os.PathLike, exclude: str | os.PathLike | None = None,
                suffixes: tuple[str, ...] | None = None) -> str | None:
    """SHA-256 (hex) of a file's bytes, or of a folder's files (relative names and bytes; names starting
    with "." are skipped: locks and temporary files; so is the folder ``exclude``, e.g. a run folder kept
    inside its data folder; with ``suffixes``, only files whose names end so); None when ``path`` does not
    exist."""
    path = Path(path)
    if not path.exists():
        return None
    if path.is_file():
        files = [path]
    else:
        skip = None if exclude is None else Path(exclude).resolve()
        files = sorted(p for p in path.rglob("*") if p.is_file()
                       and not any(s.startswith(".") for s in p.relative_to(path).parts)
                       and (skip is None or not p.resolve().is_relative_to(skip))
                       and (suffixes is None or p.name.endswith(suffixes)))
    h = hashlib.sha256()
    for f in files:
        h.update(f.relative_to(path).as_posix().encode() + b"\0")
        with open(f, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
        h.update(b"\0")
    return h.hexdigest()


def code_digest() -> str:
    """SHA-256 (hex) of this package's source and data files: a result stored by another version of the code
    is not one this version would compute."""
    return tree_digest(Path(__file__).resolve().parents[1], suffixes=(".py", ".json", ".toml"))


def json_digest(obj: Any) -> str:
    """SHA-256 (hex) of ``obj`` as canonical JSON (sorted keys; non-JSON values by their ``str``)."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


# ------------------------------------------------------------------------------------------------------ resumable state
def load_torch_file(path: str | os.PathLike, what: str = "checkpoint") -> Any:
    """``torch.load`` of a resumable state (CPU); DataError saying the file is corrupt and offering --fresh."""
    import torch

    try:
        return torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # truncated or empty files raise EOFError, RuntimeError, UnpicklingError, ...
        raise DataError(f"{path}: corrupt {what} ({_reason(exc)}); use --fresh to start over, or choose "
                        "another --out") from None


def check_npz(path: str | os.PathLike, keys: tuple[str, ...], what: str = "cache") -> None:
    """Refuse an ``.npz`` file that cannot be read or lacks one of ``keys`` (DataError offering --fresh)."""
    try:
        with np.load(path, allow_pickle=False) as d:
            for k in keys:
                d[k]  # decompresses: a truncated member fails here
    except Exception as exc:  # zipfile.BadZipFile, EOFError, KeyError, ValueError, OSError, ...
        raise DataError(f"{path}: corrupt {what} ({_reason(exc)}); use --fresh to start over, or choose "
                        "another --out") from None


def _reason(exc: Exception) -> str:
    """The exception's type and the first sentence of its message, for a one-line error."""
    first = str(exc).strip().splitlines()[0].split(". ")[0][:120] if str(exc).strip() else ""
    return f"{type(exc).__name__}: {first}" if first else type(exc).__name__


# ------------------------------------------------------------------------------------------------------ provenance
#: The file in a run folder that records what it was made from.
PROVENANCE = "provenance.json"


def provenance(data: str | os.PathLike, frames: np.ndarray, config: dict) -> dict:
    """What a run folder is made from: the data path, frame count, frame size (px), a content hash of the
    frames as used (:func:`frames_digest`) and the configuration."""
    T, H, W = frames.shape[:3]
    return {"data": str(Path(data).resolve()), "frames": int(T), "resolution": [int(W), int(H)],
            "frames_sha256": frames_digest(frames), "config": config}


def check_provenance(folder: str | os.PathLike, record: dict) -> None:
    """Refuse to continue the run folder ``folder`` with data other than the frames it was made from.

    ``record`` is :func:`provenance` of the data given now. The frames must match in count, size and
    content (a moved data folder is fine, a changed configuration is the caller's to judge). A folder with
    no record (written by an older version) is continued with a warning.
    """
    import warnings

    folder = Path(folder)
    path = folder / PROVENANCE
    if not path.is_file():
        warnings.warn(f"{folder}: no {PROVENANCE} says which data this run folder was made from; continuing it "
                      f"with {record['data']}", stacklevel=3)
        return
    try:
        old = json.loads(path.read_text())
        made_from = (old["data"], old["frames"], old["resolution"], old["frames_sha256"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise DataError(f"{path}: unreadable ({_reason(exc)}); use --fresh to start over, or choose another "
                        "--out") from None
    if made_from[1:] != (record["frames"], record["resolution"], record["frames_sha256"]):
        def describe(r: dict) -> str:
            return f"{r['frames']} frames, {r['resolution'][0]}x{r['resolution'][1]} px, content {r['frames_sha256'][:8]}"

        raise DataError(f"{folder} was made from {old['data']} ({describe(old)}); {record['data']} gives other "
                        f"frames ({describe(record)}): use --fresh to replace it, or choose another --out")
