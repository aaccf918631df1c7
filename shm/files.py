"""Shared-memory files: create, attach, release, and clean up after a killed process.

A file is named ``PREFIX-<pid>-<n>-<ns>`` so that the next start can tell the files of a dead
process (removed) from those of a live one (kept), whatever the prefix.
"""

from __future__ import annotations

import mmap
import os
import shutil
import tempfile
import time
from itertools import count
from pathlib import Path

__all__ = [
    "attach_shared_file",
    "create_shared_file",
    "release_shared_file",
    "remove_stale_files",
    "shared_dir",
    "shared_dirs",
]

_names = count()


def shared_dirs() -> list[Path]:
    """Every folder :func:`shared_dir` may pick: where a killed server's files can be."""
    env = os.environ.get("CFSR_RING_DIR")
    dirs = [Path(env)] if env else []
    return [*dirs, Path("/dev/shm"), Path(tempfile.gettempdir())]


def shared_dir(nbytes: int) -> Path:
    """Where shared files live: ``$CFSR_RING_DIR``, else ``/dev/shm`` if it has room for
    ``nbytes`` twice over (it is RAM), else the temporary folder."""
    env = os.environ.get("CFSR_RING_DIR")
    if env:
        return Path(env)
    shm = Path("/dev/shm")
    try:
        if shm.is_dir() and shutil.disk_usage(shm).free > 2 * nbytes:
            return shm
    except OSError:
        pass
    return Path(tempfile.gettempdir())


def create_shared_file(
    prefix: str, size: int, directory: str | os.PathLike | None = None
) -> tuple[Path, mmap.mmap]:
    """Create and map a new ``PREFIX-<pid>-...`` shared-memory file of ``size`` bytes.

    Files left by a killed process are removed first; the name is unique per process and call.
    """
    d = Path(directory) if directory is not None else shared_dir(size)
    remove_stale_files(d, prefix)
    path = d / f"{prefix}-{os.getpid()}-{next(_names)}-{time.monotonic_ns() % 10**9}"
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        os.ftruncate(fd, size)
        mm = mmap.mmap(fd, size, mmap.MAP_SHARED, mmap.PROT_READ | mmap.PROT_WRITE)
    finally:
        os.close(fd)
    return path, mm


def attach_shared_file(path: str | os.PathLike) -> mmap.mmap:
    """Map an existing shared-memory file made by :func:`create_shared_file`, read-write."""
    fd = os.open(Path(path), os.O_RDWR)
    try:
        return mmap.mmap(
            fd, os.fstat(fd).st_size, mmap.MAP_SHARED, mmap.PROT_READ | mmap.PROT_WRITE
        )
    finally:
        os.close(fd)


def release_shared_file(mm: mmap.mmap, path: Path, owner: bool) -> None:
    """Unmap ``mm``; the creating process also deletes the file."""
    try:
        mm.close()
    except BufferError:
        pass  # a consumer still holds a view; the mapping goes with the process
    if owner:
        try:
            path.unlink()
        except FileNotFoundError:
            pass


def remove_stale_files(directory: str | os.PathLike, prefix: str) -> int:
    """Delete ``PREFIX-<pid>-*`` files whose creating process is gone (a killed service)."""
    n = 0
    try:
        entries = list(Path(directory).glob(prefix + "-*"))
    except OSError:
        return 0
    for p in entries:
        try:
            pid = int(p.name[len(prefix) + 1 :].split("-", 1)[0])
        except ValueError:
            continue
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            try:
                p.unlink()
                n += 1
            except OSError:
                pass
        except PermissionError:
            pass
    return n
