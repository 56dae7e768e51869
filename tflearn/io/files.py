"""Atomic file writes: an artefact is either its old version or its new one, never half
written. Each writer writes a temporary file in the target's folder, flushes it to disk
and renames it over the target (``os.replace`` is atomic on POSIX and Windows). The
artefact gets the permissions a plain ``open(path, "w")`` would give it: a new file
0o666 less the umask (0644 under the usual umask 022), a rewritten one keeps its own.

:func:`locked` makes one process at a time the writer of an output folder."""
from __future__ import annotations

import contextlib
import os
import secrets
import stat
from pathlib import Path

from ..errors import InputError


@contextlib.contextmanager
def replacing(path):
    """``with replacing(path) as tmp:`` write to the file ``tmp`` (hidden, in the same
    folder, ending in ``.tmp`` + path's suffix so that writers that go by the extension
    still work); on success it replaces ``path`` atomically, on an exception it is
    removed and ``path`` is untouched."""
    path = Path(path)
    tmp = _new_file(path)
    try:
        if path.exists():                    # a rewritten file keeps its permissions
            os.chmod(tmp, stat.S_IMODE(path.stat().st_mode))
        yield tmp
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
        _fsync_folder(path.parent)
    finally:
        tmp.unlink(missing_ok=True)


def _new_file(path: Path) -> Path:
    """A new, empty hidden file beside ``path``, made as ``open`` makes one: 0o666 less
    the umask (``os.open`` applies it)."""
    while True:
        tmp = path.parent / f".{path.name}.{secrets.token_hex(4)}.tmp{path.suffix}"
        try:
            os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
            return tmp
        except FileExistsError:
            continue


def _fsync_folder(folder: Path) -> None:
    """Make a rename in ``folder`` durable (POSIX; elsewhere folders cannot be opened)."""
    if os.name == "posix":
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def write_bytes(path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with replacing(path) as tmp:
        tmp.write_bytes(data)


def write_text(path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    write_bytes(path, text.encode("utf-8"))


#: The lock file :func:`locked` keeps in an output folder while a process writes there.
LOCK_FILE = ".tflearn.lock"


class FolderLocked(InputError):
    """Another live process is writing into the output folder (:func:`locked`)."""


@contextlib.contextmanager
def folder(path):
    """``with folder(path):`` the folder ``path`` exists (made with its parents if
    needed); on leaving, the folders made here that are still empty are removed again, so
    that a command that failed before writing anything leaves no empty folder. Yields the
    folders made, the outermost last ([] when ``path`` existed)."""
    path = Path(path)
    made = [p for p in (path, *path.parents) if not p.exists()]
    path.mkdir(parents=True, exist_ok=True)
    try:
        yield made
    finally:
        for p in made:
            with contextlib.suppress(OSError):     # not empty: something was written there
                p.rmdir()


@contextlib.contextmanager
def locked(out):
    """``with locked(out):`` this process alone writes into the folder ``out`` (made as
    by :func:`folder`): an exclusive lock on ``out``/:data:`LOCK_FILE`, which holds the
    holder's pid. The lock is the operating system's (``flock``; ``msvcrt.locking`` on
    Windows), so it ends with its process however that ends: a lock file left by a killed
    run is taken over. Raises :class:`FolderLocked` naming the folder and the holder's
    pid while another process holds it. On leaving, the lock file is removed."""
    with folder(out):
        path = Path(out) / LOCK_FILE
        while True:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
            try:
                _lock(fd)
            except OSError:
                os.lseek(fd, 0, os.SEEK_SET)
                holder = os.read(fd, 32).decode("ascii", "replace").strip() or "unknown"
                os.close(fd)
                raise FolderLocked(f"{out}: another process (pid {holder}) is writing into this "
                                   f"folder; wait for it to end, or choose another output folder") from None
            try:
                same = os.path.samestat(os.fstat(fd), os.stat(path))
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)             # its last holder removed it as we opened it: lock the new one
        try:
            os.ftruncate(fd, 0)
            os.write(fd, f"{os.getpid()}\n".encode("ascii"))
            yield path
        finally:
            with contextlib.suppress(OSError):      # (Windows removes no open file: it stays)
                path.unlink()
            os.close(fd)


def _lock(fd: int) -> None:
    """Lock the open file ``fd`` exclusively without waiting; OSError if another process
    holds it."""
    try:
        import fcntl
    except ImportError:                          # Windows: a byte past the pid, left readable
        import msvcrt
        os.lseek(fd, 64, os.SEEK_SET)
        msvcrt.locking(fd, msvcrt.LK_NBLCK, 1)
        os.lseek(fd, 0, os.SEEK_SET)
    else:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
