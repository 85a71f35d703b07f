"""Saved files — policies and checkpoints — hold tensors and plain data only, never code.

`save` writes atomically (a run killed while saving keeps the previous file) and turns NumPy
arrays into tensors tagged to come back as arrays; `load` reads with
`torch.load(weights_only=True)`, which refuses any pickled Python object, so a `policy.pt` or
`checkpoint.pt` from someone else cannot run code on this machine. Before that, the file must be a
whole torch archive: each member's checksum is verified, so random bytes or a file damaged
anywhere are refused as such. Every failure is a `ValueError` naming the file. The temporary file
of a write killed midway is removed by the next write of the same file.
"""

from __future__ import annotations

import glob
import hashlib
import os
import pickle
import re
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

_NUMPY = "__numpy__"
"""Key of a one-entry dict that stands for a NumPy array (its data as a tensor)."""


def _plain(obj: Any) -> Any:
    """`obj` with NumPy arrays as tagged tensors, NumPy scalars as Python numbers and tensors
    on the CPU (a run on an accelerator writes files any machine reads)."""
    if isinstance(obj, torch.Tensor) and obj.device.type != "cpu":
        return obj.cpu()
    if isinstance(obj, np.ndarray):
        return {_NUMPY: torch.from_numpy(np.ascontiguousarray(obj))}
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, dict):  # dict or OrderedDict (a state_dict), kept as it is
        return type(obj)((k, _plain(v)) for k, v in obj.items())
    if isinstance(obj, list | tuple):
        return type(obj)(_plain(v) for v in obj)
    return obj


def _restore(obj: Any) -> Any:
    if isinstance(obj, dict):
        if len(obj) == 1 and _NUMPY in obj:
            return obj[_NUMPY].numpy()
        return type(obj)((k, _restore(v)) for k, v in obj.items())
    if isinstance(obj, list | tuple):
        return type(obj)(_restore(v) for v in obj)
    return obj


def _atomically(path: str | Path, write: Callable[[Path], None]) -> None:
    """`write` a temporary file beside `path` (unique per process), then move it over `path`:
    a reader, a resumed run or a kill sees the whole old file or the whole new one."""
    path = Path(path)
    tmp = path.with_name(f"{path.name}.tmp{os.getpid()}")
    _remove_stale(path)
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)  # a failed write leaves nothing behind


def _remove_stale(path: Path) -> None:
    """Delete the temporary files of `path` left by processes killed while writing it (a live
    writer's file is left alone)."""
    for stale in path.parent.glob(f"{glob.escape(path.name)}.tmp*"):
        pid = stale.name[len(path.name) + 4 :]
        if pid.isdigit() and not _alive(int(pid)):
            stale.unlink(missing_ok=True)


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return False  # this process writes one file at a time: its own leftover is stale
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def save(obj: dict[str, Any], path: str | Path) -> None:
    """Write `obj` (tensors, NumPy arrays, numbers, strings, lists, tuples, dicts) to `path`."""
    _atomically(path, lambda tmp: torch.save(_plain(obj), tmp))


def write_text(path: str | Path, text: str) -> None:
    """Write a text file atomically, as given (a CSV keeps its \\r\\n)."""
    _atomically(path, lambda tmp: tmp.write_text(text, newline=""))


def _check_archive(path: Path, what: str) -> None:
    """`path` is a whole torch archive (a zip whose every member has its checksum): random bytes
    and a file damaged anywhere are refused before anything is unpickled."""
    if path.stat().st_size == 0:
        raise ValueError(f"{path}: not a readable {what} (an empty file)")
    if not zipfile.is_zipfile(path):
        raise ValueError(
            f"{path}: not a readable {what} (not a torch archive: random bytes, another "
            "format, or a file cut short)"
        )
    try:
        with zipfile.ZipFile(path) as archive:
            damaged = archive.testzip()
    except (zipfile.BadZipFile, OSError, UnicodeDecodeError, ValueError) as e:
        raise ValueError(f"{path}: not a readable {what} (corrupt archive: {e})") from None
    if damaged is not None:
        raise ValueError(f"{path}: not a readable {what} (corrupt: member {damaged!r} is damaged)")


def load(path: str | Path, what: str = "file") -> dict[str, Any]:
    """Read a file written by `save`; `what` names it in errors ("checkpoint", "policy")."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"no {what} at {path}")
    _check_archive(path, what)
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:
        found = re.findall(r"GLOBAL (\S+) was not an allowed global", str(e))
        raise ValueError(
            f"{path}: refused to load this {what}: it holds pickled Python objects, not only "
            "tensors and plain data, and loading those could run code"
            + (f" (the first: {found[0]})" if found else "")
            + "; checkpoints written by marlmerge 0.2 are of this kind: train them again"
        ) from None
    except Exception as e:  # any other failure of a damaged file names the file
        raise ValueError(f"{path}: not a readable {what} (truncated or corrupt: {e})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: not a marlmerge {what} (holds a {type(data).__name__})")
    return _restore(data)


def saved_digest(path: str | Path | None, name: str) -> str:
    """A short SHA-256 of the saved file that `path` names: the file itself, or `name` inside a
    run folder ("" for None, or a path that is neither, such as the edge driver's name). A
    result cached under a key that holds it is recomputed when the file changes, as when a
    run is trained again into the same folder."""
    if path is None:
        return ""
    p = Path(path)
    p = p if p.is_file() else p / name
    return hashlib.sha256(p.read_bytes()).hexdigest()[:16] if p.is_file() else ""
