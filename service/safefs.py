"""Files the service writes into the data folder: created exclusively, never through a link,
always inside the folder.

Every file the service creates (a recording, its sidecar, the folder's lock) goes through
here. A folder below the data folder is opened one component at a time with ``O_NOFOLLOW``
relative to the data folder's own descriptor, so a component that is a symbolic link (a
``recordings`` that points elsewhere) is refused instead of followed, and the opened folder is
checked to lie inside the data folder. Files are then created relative to that descriptor with
``O_CREAT | O_EXCL | O_NOFOLLOW``: a name that exists in any form (a file another server is
recording into, a dangling link) is refused, never truncated or followed. A sidecar is written
to a fresh temporary name the same way and renamed over its final name: the rename replaces a
link instead of writing through it, and a reader sees the old sidecar or the whole new one.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import secrets
import stat
from pathlib import Path
from typing import Any

__all__ = [
    "FolderLock",
    "UnsafePathError",
    "create_exclusive",
    "name_taken",
    "open_subfolder",
    "write_bytes_at",
    "write_json_at",
]

_DIR_FLAGS = os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC
_NEW_FILE = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC


class UnsafePathError(OSError):
    """A folder or file the service would write is a symbolic link, not a folder, or lies
    outside the data folder."""


def _check_name(name: str) -> None:
    if not name or name in (".", "..") or "/" in name or "\0" in name:
        raise UnsafePathError(f"{name!r} is not a plain file name")


def _fd_path(fd: int) -> Path | None:
    """The path the kernel has for ``fd`` (Linux ``/proc``); None where that is unknown."""
    try:
        return Path(os.readlink(f"/proc/self/fd/{fd}"))
    except OSError:
        return None


def open_subfolder(root: Path, rel: str, *, create: bool = True) -> int:
    """A descriptor of the folder ``root/rel`` (``rel``: names separated by ``/``), made if
    missing when ``create``; UnsafePathError when a component is a link or not a folder, or
    the result is not inside ``root``. The caller closes the descriptor."""
    root = Path(root).resolve()
    fd = os.open(root, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    try:
        for part in [p for p in rel.split("/") if p]:
            _check_name(part)
            if create:
                with contextlib.suppress(FileExistsError):
                    os.mkdir(part, 0o755, dir_fd=fd)
            try:
                sub = os.open(part, _DIR_FLAGS, dir_fd=fd)
            except OSError as exc:
                if exc.errno in (errno.ELOOP, errno.ENOTDIR):
                    link = stat.S_ISLNK(os.lstat(part, dir_fd=fd).st_mode)
                    kind = "a symbolic link" if link else "not a folder"
                    raise UnsafePathError(
                        f"{root.name}/{rel} cannot hold recordings: {part} is {kind} (the "
                        "service writes only into real folders inside the data folder)"
                    ) from None
                raise
            os.close(fd)
            fd = sub
        where = _fd_path(fd)
        if where is not None and where != root and root not in where.parents:
            raise UnsafePathError(f"{rel} resolves to {where}, outside the data folder {root}")
        return fd
    except BaseException:
        os.close(fd)
        raise


def name_taken(dir_fd: int, name: str) -> bool:
    """Whether ``name`` exists in the folder in any form (a dangling link counts)."""
    try:
        os.lstat(name, dir_fd=dir_fd)
    except FileNotFoundError:
        return False
    return True


def create_exclusive(dir_fd: int, name: str, mode: int = 0o644) -> int:
    """A new, empty file ``name`` in the folder, opened for writing; FileExistsError if the
    name exists in any form (a file, a folder, a link, dangling or not)."""
    _check_name(name)
    return os.open(name, _NEW_FILE, mode, dir_fd=dir_fd)


def write_json_at(dir_fd: int, name: str, obj: Any, *, default=None) -> None:
    """Write ``obj`` as JSON to ``name`` in the folder atomically: a fresh temporary file
    (exclusive, unpredictable name) renamed over ``name``, which replaces a link rather than
    writing through it."""
    write_bytes_at(dir_fd, name, json.dumps(obj, indent=2, default=default).encode())


def write_bytes_at(dir_fd: int, name: str, text: bytes) -> None:
    """Write ``text`` to ``name`` in the folder atomically (as :func:`write_json_at`)."""
    _check_name(name)
    tmp = f".{name}.{secrets.token_hex(6)}.tmp"
    fd = create_exclusive(dir_fd, tmp)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, name, src_dir_fd=dir_fd, dst_dir_fd=dir_fd)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp, dir_fd=dir_fd)
        raise


class FolderLock:
    """An advisory lock on a folder (``.cfsr-serve.lock`` inside it) that says which server
    holds it; a second server learns the first one's pid instead of failing.

    ``holder`` is None when this process took the lock, else the pid written by the server
    that holds it (0 if unreadable). The lock lasts as long as the object (or the process).
    """

    NAME = ".cfsr-serve.lock"

    def __init__(self, folder: Path) -> None:
        self.holder: int | None = None
        dfd = os.open(Path(folder), os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
        try:
            self._fd = os.open(self.NAME, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC,
                               0o644, dir_fd=dfd)
        finally:
            os.close(dfd)
        try:
            fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            try:
                self.holder = int(os.pread(self._fd, 32, 0).decode().strip() or 0)
            except (OSError, ValueError):
                self.holder = 0
            return
        os.ftruncate(self._fd, 0)
        os.pwrite(self._fd, f"{os.getpid()}\n".encode(), 0)

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1
