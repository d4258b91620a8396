"""Writing inside a results folder (design §7): one writer, no symlink followed, whole rows only.

Every file a run writes goes through this module:

- :func:`check_out_dir` checks a results folder a command is given (``--out``) before a run
  starts: not a symbolic link, and writable (a probe file created in it and removed).
- :func:`open_dir` and :func:`open_file` open a folder or a file without following a symbolic
  link at its last component (``O_NOFOLLOW``), the file relative to its folder's descriptor, so
  a link planted in a results folder (``logs/agent-1.log -> ../../victim``) is refused
  (:class:`SymlinkRefused`) instead of written through. The folder's own ancestors are the
  user's path and are resolved as usual.
- :func:`write_atomic` replaces a file through a temporary file in the same folder and a
  rename; an error names the file meant, never the temporary one.
- :class:`AppendFile` appends whole records: a failed or short write is cut back to where the
  append began before the error is raised, so a full disk never leaves half a row.
- :class:`FolderLock` is the one-writer rule: an ``flock`` on :data:`LOCK_FILE` in the folder,
  held for as long as a run (or ``--resume``) writes there. The kernel releases it when its
  holder dies, so a stale lock never blocks a new run, and a live holder's lock is never broken.
"""
from __future__ import annotations

import errno
import fcntl
import json
import os
import secrets
import socket
import stat
import time
from pathlib import Path

from protocol.cli import Refused, describe
from protocol.limits import MAX_TEXT

LOCK_FILE = ".swarm.lock"
"""The lock file in a results folder (kept between runs: deleting it would let two writers
lock two different files)."""
MAX_HOLDER_BYTES = 1024  # the holder's note is about 100 bytes
HOLDER_WAIT_S = 1.0  # how long a refused writer waits for the holder's note
SCAN_DEPTH = 2  # a results folder, and its logs/, state/, figures/ folders
_DIR_FLAGS = os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC


class SymlinkRefused(OSError):
    """A path a run would write to is a symbolic link (or passes through one in the folder)."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        super().__init__(errno.ELOOP, "refusing to write through a symbolic link (a run "
                                      "writes only inside its folder)", str(path))


class FolderBusy(Refused):
    """Another live process holds the folder's lock; the message names it."""


class FolderRefused(Refused):
    """A results folder a run must not write into (it holds a symbolic link)."""


def _named(exc: OSError, path: str | os.PathLike[str]) -> OSError:
    """``exc`` naming ``path`` (a link found by ``O_NOFOLLOW`` as :class:`SymlinkRefused`:
    Linux says ``ELOOP`` for a file, ``ENOTDIR`` for a folder)."""
    if exc.errno == errno.ELOOP or (exc.errno == errno.ENOTDIR and os.path.islink(path)):
        return SymlinkRefused(path)
    return OSError(exc.errno, exc.strerror, str(path))


def open_dir(path: str | os.PathLike[str]) -> int:
    """A descriptor of the folder ``path`` (created with its parents if missing), refusing a
    symbolic link as its last component. Close it with ``os.close``."""
    path = Path(path)
    try:
        return os.open(path, _DIR_FLAGS)
    except FileNotFoundError:
        pass
    except OSError as exc:
        raise _named(exc, path) from None
    try:
        os.makedirs(path, exist_ok=True)
        return os.open(path, _DIR_FLAGS)
    except OSError as exc:
        raise _named(exc, path) from None


def check_out_dir(path: str | os.PathLike[str], flag: str = "--out") -> Path:
    """Make sure ``path`` is, or can be created as, a folder this process can write into.

    The folder is created (with its parents) if missing, then a probe file is created in it,
    without following a symbolic link, and removed.

    Raises
    ------
    FolderRefused
        ``path`` is a symbolic link (a run writes only inside its folder).
    ValueError
        Naming ``flag`` and the reason: ``path`` is a file, cannot be created (e.g. under
        ``/proc``), is not writable (read-only or full file system), or is too long or
        unprintable to be announced in the run's ``done`` message.
    """
    path = Path(path)
    text = str(path)
    if len(text) > MAX_TEXT or not text.isprintable():
        raise ValueError(f"{flag} must be a printable path of at most {MAX_TEXT} characters")
    if path.is_symlink():
        raise FolderRefused(f"{flag} {path} is a symbolic link; give the real folder")
    if path.exists() and not path.is_dir():
        raise ValueError(f"{flag} {path} is a file, not a folder")
    try:
        folder = open_dir(path)
        try:
            probe = f".write-check.{secrets.token_hex(4)}"
            fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW
                         | os.O_CLOEXEC, 0o600, dir_fd=folder)
            try:
                _write_all(fd, b"\n")
            finally:
                os.close(fd)
                os.unlink(probe, dir_fd=folder)
        finally:
            os.close(folder)
    except OSError as exc:
        raise ValueError(f"{flag} {path} cannot hold results: {describe(exc)}") from None
    return path


def open_file(path: str | os.PathLike[str], flags: int, mode: int = 0o644) -> int:
    """``os.open`` of ``path`` relative to its folder's descriptor, never following a symbolic
    link (in the file's name or its folder's); the folder is created if missing."""
    path = Path(path)
    folder = open_dir(path.parent)
    try:
        return os.open(path.name, flags | os.O_NOFOLLOW | os.O_CLOEXEC, mode, dir_fd=folder)
    except OSError as exc:
        raise _named(exc, path) from None
    finally:
        os.close(folder)


def write_atomic(path: str | os.PathLike[str], data: str | bytes, mode: int = 0o600) -> None:
    """Replace ``path`` with ``data`` (text as UTF-8) through a temporary file in the same folder
    and a rename, without following a symbolic link; an error names ``path``."""
    path = Path(path)
    raw = data.encode("utf-8") if isinstance(data, str) else data
    folder = open_dir(path.parent)
    tmp = f".{path.name}.{secrets.token_hex(4)}.tmp"
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC,
                     mode, dir_fd=folder)
        try:
            _write_all(fd, raw)
        finally:
            os.close(fd)
        if _is_link(path.name, folder):  # a rename would only replace it: say so instead
            raise OSError(errno.ELOOP, os.strerror(errno.ELOOP))
        os.replace(tmp, path.name, src_dir_fd=folder, dst_dir_fd=folder)
    except BaseException as exc:
        try:
            os.unlink(tmp, dir_fd=folder)
        except OSError:
            pass
        if isinstance(exc, OSError):
            raise _named(exc, path) from None
        raise
    finally:
        os.close(folder)


def _is_link(name: str, folder: int) -> bool:
    try:
        return stat.S_ISLNK(os.stat(name, dir_fd=folder, follow_symlinks=False).st_mode)
    except FileNotFoundError:
        return False


def _write_all(fd: int, raw: bytes) -> None:
    """Write every byte of ``raw`` (a short write goes on; a write of nothing is a full disk)."""
    view = memoryview(raw)
    while view:
        written = os.write(fd, view)
        if written <= 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        view = view[written:]


class AppendFile:
    """A file grown by whole records only.

    Parameters
    ----------
    path : path
        The file (opened without following a symbolic link; created if missing).
    truncate : bool
        Empty it first (a fresh file); else records are added after what it holds.

    Attributes
    ----------
    size : int
        Bytes in the file after the last whole record.
    """

    def __init__(self, path: str | os.PathLike[str], truncate: bool = False) -> None:
        self.path = Path(path)
        flags = os.O_WRONLY | os.O_CREAT | (os.O_TRUNC if truncate else 0)
        self._fd = open_file(self.path, flags)
        self.size = os.lseek(self._fd, 0, os.SEEK_END)

    def append(self, data: bytes) -> None:
        """Add ``data`` whole, or not at all: a failed or short write is cut back to the file's
        size before it, then the error (naming the file) is raised."""
        start = self.size
        try:
            _write_all(self._fd, data)
        except OSError as exc:
            self.cut(start)
            raise _named(exc, self.path) from None
        self.size = start + len(data)

    def cut(self, size: int) -> None:
        """Cut the file back to ``size`` bytes (the end of a whole record) and write there next.
        Cutting never needs disk space, so it works on a full disk."""
        os.ftruncate(self._fd, size)
        os.lseek(self._fd, size, os.SEEK_SET)
        self.size = size

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1


def refuse_symlinks(folder: str | os.PathLike[str], depth: int = SCAN_DEPTH) -> None:
    """Raise :class:`FolderRefused` if ``folder`` is a symbolic link or holds one within
    ``depth`` levels (the files and sub-folders a run writes)."""
    folder = Path(folder)
    if folder.is_symlink():
        raise FolderRefused(f"{folder} is a symbolic link; give the real folder")
    level = [folder]
    for _ in range(depth):
        below = []
        for path in level:
            try:
                entries = list(os.scandir(path))
            except FileNotFoundError:
                continue
            for entry in entries:
                if entry.is_symlink():
                    raise FolderRefused(
                        f"{folder} holds a symbolic link, {entry.path} -> "
                        f"{os.readlink(entry.path)}: a run writes only inside its folder; "
                        "remove the link or choose another folder (no results were written)")
                if entry.is_dir(follow_symlinks=False):
                    below.append(Path(entry.path))
        level = below


class FolderLock:
    """The one-writer lock of a results folder (design §7).

    :meth:`acquire` takes an exclusive ``flock`` on ``folder/.swarm.lock`` without waiting and
    writes who holds it (run id, process id, host) into the file; a second writer gets
    :class:`FolderBusy` naming that holder. The lock lasts until :meth:`release` or the death
    of the holding process. Its descriptor is not inherited by child processes.

    Parameters
    ----------
    folder : path
        The results folder (created if missing).
    run_id : str
        The run that will write there (shown to a refused writer).
    """

    def __init__(self, folder: str | os.PathLike[str], run_id: str) -> None:
        self.folder, self.run_id = Path(folder), run_id
        self._fd = -1

    def acquire(self) -> FolderLock:
        """Take the lock, then check the folder holds no symbolic link (under the lock).

        Raises
        ------
        FolderBusy
            Another process holds it.
        FolderRefused
            The folder holds a symbolic link.
        """
        try:
            fd = open_file(self.folder / LOCK_FILE, os.O_RDWR | os.O_CREAT)
        except SymlinkRefused as exc:
            raise FolderRefused(f"{exc.filename} is a symbolic link: a run writes only inside "
                                "its folder; remove the link or choose another folder") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _holder(fd)
            os.close(fd)
            raise FolderBusy(f"{self.folder} is in use by {holder}: one writer per results "
                             "folder; wait for it to end or choose another folder") from None
        except BaseException:
            os.close(fd)
            raise
        self._fd = fd
        try:
            refuse_symlinks(self.folder)
            note = json.dumps({"run_id": self.run_id, "pid": os.getpid(),
                               "host": socket.gethostname()}).encode() + b"\n"
            os.pwrite(fd, note, 0)  # the first line is read back: never half a note
            os.ftruncate(fd, len(note))
        except BaseException:
            self.release()
            raise
        return self

    def release(self) -> None:
        """Give the lock up (closing the descriptor releases the ``flock``)."""
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    def __enter__(self) -> FolderLock:
        return self.acquire()

    def __exit__(self, *exc_info) -> None:
        self.release()


def _holder(fd: int) -> str:
    """Who holds the lock on ``fd``, from the note its holder wrote. The holder writes it just
    after taking the lock: a note that is missing or names a dead process of this host is the
    previous holder's, and is read again for up to :data:`HOLDER_WAIT_S`."""
    deadline = time.monotonic() + HOLDER_WAIT_S
    while True:
        try:
            note = json.loads(os.pread(fd, MAX_HOLDER_BYTES, 0).split(b"\n")[0])
            run_id, pid, host = str(note["run_id"]), int(note["pid"]), str(note["host"])[:64]
        except (OSError, ValueError, TypeError, KeyError):
            pass
        else:
            if host != socket.gethostname() or _alive(pid):
                return f"run {run_id!r} (pid {pid} on host {host!r})"
        if time.monotonic() > deadline:
            return "another process (it has not said which yet)"
        time.sleep(0.05)


def _alive(pid: int) -> bool:
    """Whether process ``pid`` of this host exists."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # it exists, as another user's
        return True
    return True
