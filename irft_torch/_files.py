"""Saving files so that a failure never leaves a damaged one: every file the package writes (model
files, datasets, figures, logs, ``irft fit``'s output folder) goes to a temporary file in the same
folder, is flushed to disk (fsync) and only then renamed over the old one (``os.replace``, atomic on
POSIX and Windows). A full disk, a file-size limit, Ctrl-C or a crash while writing leaves the
previous file as it was (and no temporary behind, except after a hard kill).

Paths that are not regular files (``/dev/null``, ``/dev/full``, a pipe) are written directly; a
folder given as a file, a missing folder or a failed write is an ``OSError`` that names the path
and says the previous file is unchanged.
"""

from __future__ import annotations

import contextlib
import errno
import os
import secrets
import stat
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import BinaryIO

__all__ = ["atomic_path", "atomic_write", "StagedFiles", "SaveError", "checked_target", "temp_name"]


class SaveError(OSError):
    """A file could not be written; the previous file at that path (if any) is unchanged. ``str`` is
    the message alone (no ``[Errno n]`` prefix); ``errno`` holds the code."""

    def __init__(self, code: int, message: str) -> None:
        super().__init__(message)
        self.errno, self.strerror = code, message

    def __str__(self) -> str:
        return str(self.strerror)


def _special(path: Path) -> bool:
    """An existing path that is not a regular file (a device, a pipe): written in place."""
    try:
        mode = path.stat().st_mode
    except OSError:
        return False
    return not stat.S_ISREG(mode) and not stat.S_ISDIR(mode)


def checked_target(path, what: str) -> Path:
    """``path`` checked as a file to write (a folder, or a missing folder, is a ``SaveError``); a
    symlink is followed to the file it names."""
    path = Path(path)
    if path.is_symlink():  # replace the file the link points at, not the link
        path = path.resolve()
    if path.is_dir():
        raise SaveError(errno.EISDIR, f"cannot save the {what} to {path}: it is a folder; give a file name "
                                      f"(e.g. {path / ('model.pt' if what == 'model' else 'out')})")
    if not _special(path) and not path.parent.is_dir():
        raise SaveError(errno.ENOENT, f"cannot save the {what} to {path}: there is no folder {path.parent}")
    return path


def _fail(e: OSError, path: Path, what: str, special: bool) -> SaveError:
    if isinstance(e, SaveError):
        return e
    why = e.strerror or str(e)
    keep = "" if special else " (the previous file, if any, is unchanged)"
    return SaveError(e.errno or errno.EIO, f"cannot save the {what} to {path}: {why}{keep}")


def _os_error_in(e: BaseException) -> OSError | None:
    """The OSError an exception was raised while handling (its context chain), if any."""
    seen = set()
    while e is not None and id(e) not in seen:
        if isinstance(e, OSError):
            return e
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return None


def _fsync_dir(folder: Path) -> None:
    with contextlib.suppress(OSError):  # not every file system (or OS) can sync a folder
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


@contextlib.contextmanager
def _no_interrupt() -> Iterator[None]:
    """SIGINT held back (delivered on leaving) where signal masks exist; else nothing."""
    import signal
    import threading

    if not hasattr(signal, "pthread_sigmask") or threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def temp_name(path: Path) -> Path:
    """A hidden, unique temporary name beside ``path`` with the same suffix."""
    # hidden, unique, and with the same suffix (writers such as python-can pick the format by it)
    return path.with_name(f".{path.stem}.{os.getpid()}-{secrets.token_hex(3)}.tmp{path.suffix}")


@contextlib.contextmanager
def atomic_path(path, what: str = "file") -> Iterator[Path]:
    """A temporary path beside ``path`` to write to; on leaving the block without an error it is
    fsynced and renamed over ``path``, on any error (Ctrl-C included) deleted, ``path`` untouched.

    Example:
        >>> with atomic_path("fig.png", "figure") as tmp:
        ...     fig.savefig(tmp)
    """
    path = checked_target(path, what)
    if _special(path):
        try:
            yield path
        except OSError as e:
            raise _fail(e, path, what, True) from None
        return
    tmp = temp_name(path)
    try:
        yield tmp
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except OSError as e:
        raise _fail(e, path, what, False) from None
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink()
    _fsync_dir(path.parent)


def atomic_write(path, write: Callable[[BinaryIO], None], what: str = "file") -> Path:
    """Call ``write(fh)`` on a binary file handle and put the result at ``path`` atomically (see the
    module): the previous file stays whole if ``write`` or the disk fails. Returns the path written.

    Example:
        >>> atomic_write("model.pt", lambda fh: torch.save(obj, fh), "model")
    """
    path = checked_target(path, what)
    special = _special(path)
    with atomic_path(path, what) as tmp:
        try:
            with open(tmp, "wb") as fh:
                write(fh)
                fh.flush()
                if special:
                    with contextlib.suppress(OSError):  # a device may not sync; its write errors came above
                        os.fsync(fh.fileno())
        except OSError as e:
            raise _fail(e, path, what, special) from None
        except Exception as e:  # a writer that turns a failed write into its own error (torch's zip writer)
            cause = _os_error_in(e)
            if cause is None:
                raise
            raise _fail(cause, path, what, special) from None
    return path


class StagedFiles:
    """Several files that must change together (a model and the figures made from it): each is
    written to a temporary beside its final name; ``commit`` renames them all, one after another,
    under an exclusive lock on the folder (so two processes saving into one folder never interleave:
    the folder holds one run's set or the other's); leaving the block without a commit (an error,
    Ctrl-C) deletes the temporaries and leaves the folder as it was.

    Example:
        >>> with StagedFiles(out) as staged:
        ...     model.save(staged.path("model.pt"))
        ...     fig.savefig(staged.path("stress_map.png"))
        ...     staged.commit()
    """

    LOCK = ".irft.lock"

    def __init__(self, folder) -> None:
        self.folder = Path(folder)
        self._temps: dict[str, Path] = {}
        self.committed = False

    def path(self, name: str) -> Path:
        """The temporary to write ``name`` to (``name`` is a file name inside the folder)."""
        if name not in self._temps:
            self._temps[name] = temp_name(self.folder / name)
        return self._temps[name]

    @contextlib.contextmanager
    def locked(self) -> Iterator[None]:
        """An exclusive lock on the folder (advisory, ``flock``; a no-op where it does not exist)."""
        try:
            import fcntl
        except ImportError:  # not POSIX: renames are still atomic one by one
            yield
            return
        with open(self.folder / self.LOCK, "a") as fh:
            fcntl.flock(fh, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(fh, fcntl.LOCK_UN)

    def commit(self, check: Callable[[], bool] | None = None) -> bool:
        """fsync every temporary, then (under the lock) call ``check()`` if given (False: keep the
        folder as it is and return False) and rename each over its final name."""
        try:
            for tmp in self._temps.values():
                with open(tmp, "rb+") as fh:
                    os.fsync(fh.fileno())
            with self.locked():
                if check is not None and not check():
                    return False
                with _no_interrupt():  # the renames take microseconds: Ctrl-C waits for the last one
                    for name, tmp in self._temps.items():
                        os.replace(tmp, self.folder / name)
        except OSError as e:
            raise SaveError(e.errno or errno.EIO, f"cannot save into {self.folder}: {e.strerror or e} (the files "
                                                  "there are unchanged)") from None
        _fsync_dir(self.folder)
        self.committed = True
        return True

    def __enter__(self) -> StagedFiles:
        return self

    def __exit__(self, *exc) -> None:
        for tmp in self._temps.values():
            with contextlib.suppress(OSError):
                tmp.unlink()
