"""Atomic file writes, their leftovers, and one writer per folder.

A file is written to a hidden temporary in the target's folder, then renamed onto it
(``os.replace``): an interrupted run leaves either the old file or the new one, never half of
one. A temporary's name carries its owner's process id, ``.<name>.<pid>.<random><suffix>``, so
that `remove_stale_temporaries` removes only those whose process is gone, never a file
another live run is writing. `folder_lock` keeps a second run out of a folder that a run
is writing (``fcntl.flock`` on ``<folder>/.lock``; released by the kernel when the process
ends, however it ends; the file is removed when the ``with`` block ends).
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import shutil
import tempfile
from pathlib import Path
from typing import Iterator

try:
    import fcntl
except ImportError:  # pragma: no cover - not on Windows: no locking there
    fcntl = None

#: The lock file `folder_lock` holds in a folder.
LOCK_NAME = ".lock"

# .<name>.<pid>.<8 random characters of mkstemp/mkdtemp><suffix>
_TEMPORARY = re.compile(r"^\.(?P<name>.+)\.(?P<pid>\d+)\.[a-z0-9_]{8}(?P<suffix>\..+)?$")


class FolderBusyError(RuntimeError):
    """Another process holds the folder's lock (`folder_lock`)."""


def temporary_prefix(path: str | os.PathLike) -> str:
    """The prefix of a temporary for ``path``: hidden, with this process's id."""
    return f".{Path(path).name}.{os.getpid()}."


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:   # another user's live process
        return True
    return True


def remove_stale_temporaries(root: str | os.PathLike) -> list[Path]:
    """Remove the temporaries (files and staging folders, named by `temporary_prefix`)
    under ``root`` whose owner process no longer runs; a live run's are left alone. Returns
    the paths removed."""
    removed = []
    for path in sorted(Path(root).rglob(".*")):
        match = _TEMPORARY.match(path.name)
        if match is None or _alive(int(match["pid"])) or not path.exists():
            continue
        _remove(path, path.is_dir() and not path.is_symlink())
        removed.append(path)
    return removed


def _remove(path: Path, folder: bool) -> None:
    """Remove a temporary file or folder, gone already or not."""
    if folder:
        shutil.rmtree(path, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()


def remove_temporaries(folders, pids) -> list[Path]:
    """Remove the temporaries (named by `temporary_prefix`) of the processes ``pids``, which
    must have ended, in ``folders`` (not below them: a quick look where they wrote, where
    `remove_stale_temporaries` walks a whole tree). Returns the paths removed."""
    pids = {int(p) for p in pids}
    removed = []
    for folder in folders:
        try:
            entries = list(os.scandir(folder))
        except (FileNotFoundError, NotADirectoryError):
            continue
        for entry in entries:
            match = _TEMPORARY.match(entry.name)
            if match is None or int(match["pid"]) not in pids:
                continue
            path = Path(entry.path)
            _remove(path, entry.is_dir(follow_symlinks=False))
            removed.append(path)
    return removed


@contextlib.contextmanager
def folder_lock(folder: str | os.PathLike) -> Iterator[Path]:
    """Hold ``folder``'s lock for the ``with`` block (the folder is created). The lock file is
    removed when the block ends, however it ends (an error, Ctrl-C); a killed process leaves
    it, and the next run takes it over (the kernel released the lock) and removes it in turn.

    The holder removes the file before it lets the lock go, and a process that locked a file
    since removed tries again on the new one, so that two processes never both hold a
    folder's lock.

    Raises:
        FolderBusyError: another process holds it; the message names the process.
    """
    folder = Path(folder)
    path = folder / LOCK_NAME
    while True:
        folder.mkdir(parents=True, exist_ok=True)
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
        except FileNotFoundError:   # the folder was removed in between: create it again
            continue
        if fcntl is None or _lock(fd, folder, path):
            break
        os.close(fd)   # locked a file its holder had removed: lock the new one
    try:
        if fcntl is not None:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode("ascii"), 0)
        yield path
    finally:
        if fcntl is not None:
            with contextlib.suppress(OSError):
                if os.stat(path).st_ino == os.fstat(fd).st_ino:
                    os.unlink(path)   # still holding it: no one else can have it yet
            os.close(fd)
        else:   # pragma: no cover - Windows: no lock, and an open file cannot be removed
            os.close(fd)
            with contextlib.suppress(OSError):
                os.unlink(path)


def _lock(fd: int, folder: Path, path: Path) -> bool:
    """Lock the open lock file ``fd``: True once held and still the file at ``path``, False
    when the file was removed (by the holder letting it go) before it was locked.

    Raises:
        FolderBusyError: another process holds it.
    """
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        owner = os.pread(fd, 32, 0).decode("ascii", "replace").strip() or "unknown"
        os.close(fd)
        raise FolderBusyError(
            f"{folder}: another run (process {owner}) is writing this folder; wait "
            f"for it to finish, or write to another folder") from None
    try:
        return os.stat(path).st_ino == os.fstat(fd).st_ino
    except FileNotFoundError:
        return False


def check_writable(path: str | os.PathLike) -> None:
    """Refuse, before any work, an output folder that cannot be created or written: a file in
    the way (the path itself or a parent), a read-only file system, no permission.

    Raises:
        OSError: with the errno and the path at fault, for the command line's one-line message.
    """
    parent = Path(path)
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if parent.exists() and not parent.is_dir():
        raise NotADirectoryError(errno.ENOTDIR, os.strerror(errno.ENOTDIR), str(parent))
    if not os.access(parent, os.W_OK | os.X_OK):
        read_only = bool(os.statvfs(parent).f_flag & os.ST_RDONLY)
        code = errno.EROFS if read_only else errno.EACCES
        raise PermissionError(code, os.strerror(code), str(parent))


def _ordinary_mode(path: str) -> None:
    """Give ``path`` the permissions of an ordinary new file (umask), not ``mkstemp``'s 0600."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(path, 0o666 & ~umask)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = ".tmp") -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it is synced and renamed onto
    ``path``, on any error removed. Creates the parent folder. The file gets the permissions of
    an ordinary new file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=temporary_prefix(path), suffix=suffix, dir=path.parent)
    os.close(fd)
    try:
        _ordinary_mode(tmp)
        yield Path(tmp)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as err:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        if isinstance(err, OSError) and err.filename is None and err.errno:
            # a write to an open file (disk full) says no path: name the one being written
            raise OSError(err.errno, err.strerror, str(path)) from err
        raise


def publish(files: list[Path], folder: str | os.PathLike) -> list[Path]:
    """Copy ``files`` into ``folder`` (created) all or nothing: each is copied to a temporary
    beside its target, and only once every copy is whole are they renamed into place; on an
    error the temporaries are removed and ``folder`` holds none of the new files. Returns the
    paths written."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    staged = []
    try:
        for file in files:
            target = folder / Path(file).name
            fd, tmp = tempfile.mkstemp(prefix=temporary_prefix(target), suffix=".tmp",
                                       dir=folder)
            os.close(fd)
            staged.append((tmp, target))
            _ordinary_mode(tmp)
            shutil.copyfile(file, tmp)
            with open(tmp, "rb+") as f:
                os.fsync(f.fileno())
        for tmp, target in staged:
            os.replace(tmp, target)
    except BaseException:
        for tmp, _ in staged:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
        raise
    return [target for _, target in staged]


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically; creates the parent folder. Returns the path."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    return atomic_write_bytes(path, text.encode("utf-8"))
