"""One writer per output (issue 15): a second `nehad video` (or `nehad batch` job, or `nehad
train`) with the same output refuses at once with a message naming the run that holds it,
instead of both working in one frame folder and one deleting it under the other.

``with output_lock(path, "nehad video"):`` takes an exclusive ``flock`` on the hidden file
``.NAME.nehad-lock`` beside `path` and writes the holder (command, pid, host, start time) into
it. The kernel releases a ``flock`` when its process ends in any way, SIGKILL included, so a
killed run never blocks the next one; the lock file itself is removed when the block ends (a
killed run's file stays, unlocked, and is reused). On shared storage, Linux NFS maps ``flock``
to NFS byte-range locks, so runs on different servers exclude each other too. Without
``fcntl`` (Windows) there is no lock.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import time
from pathlib import Path

from .errors import InputProblem

__all__ = ["LockError", "lock_file", "output_lock"]


class LockError(InputProblem, RuntimeError):
    """The output is being written by another run; the message names it."""


def lock_file(path) -> Path:
    """The lock file of `path`: ``.NAME.nehad-lock`` in the same folder."""
    path = Path(path)
    return path.parent / f".{path.name}.nehad-lock"


def _holder(lock: Path) -> str:
    try:
        info = json.loads(lock.read_text(encoding="utf-8"))
        started = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(float(info["started"])))
        return f"{info['command']} (pid {info['pid']} on {info['host']}, started {started})"
    except (OSError, ValueError, KeyError, TypeError):
        return "another nehad run"


def _acquire(lock: Path, path, error):
    """The locked file descriptor of `lock`, or None where locking is not possible."""
    import fcntl

    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise error(f"{path}: {_holder(lock)} is writing it; wait for it to finish or choose "
                        f"another output (if no such run is alive, remove {lock})") from None
        except OSError:
            os.close(fd)  # the file system has no locks (some network mounts): go without
            return None
        # the holder before us may have removed the file after we opened it: lock the file
        # that is at the path now
        try:
            same = os.stat(lock).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            return fd
        os.close(fd)


@contextlib.contextmanager
def output_lock(path, command: str, error=LockError):
    """Hold the lock of `path` for the block (module doc); raise `error` if another run holds
    it. The folder of `path` must exist (nothing is locked otherwise)."""
    try:
        import fcntl  # noqa: F401
    except ImportError:  # no flock on this platform
        fcntl = None
    lock = lock_file(path)
    fd = _acquire(lock, path, error) if fcntl is not None and lock.parent.is_dir() else None
    if fd is None:
        yield None
        return
    try:
        info = {"command": command, "pid": os.getpid(), "host": socket.gethostname(),
                "started": time.time()}
        try:
            os.ftruncate(fd, 0)
            os.write(fd, json.dumps(info).encode("utf-8"))
        except OSError:
            pass  # a full disk: the lock holds without its note of who holds it (issue 26)
        yield lock
    finally:
        with contextlib.suppress(OSError):
            os.unlink(lock)  # while still holding it (see the inode check in _acquire)
        os.close(fd)
