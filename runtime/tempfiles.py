"""Temporary files of atomic writes: names that say who wrote them, and removal of the stale ones
(docs/design.md section 10: a temporary file in the same folder, renamed over the target; issue 15).

A write to ``DIR/model.onnx`` goes through ``DIR/.model.nehad-<pid>-<host>-<random>.tmp.onnx``:
hidden, the target's name and extension (format detection by extension), and the process and
machine that wrote it. A process killed between creating and renaming it (SIGKILL, power loss)
leaves that file behind; the next write of the same target (a rerun, ``--resume``) removes it
when it is *stale*:

* written on this machine by a process that is no longer running (its pid is checked), or
* written on another machine (shared storage) and untouched for :data:`STALE_SECONDS`, or
* named in the form used before issue 15 (``.model.k3j4h5g6.tmp.onnx``, no pid) and untouched
  for :data:`STALE_SECONDS`.

A temporary file of a live writer is never removed, whatever its age. Only names of this form
are touched: nothing else in the folder is.
"""

from __future__ import annotations

import contextlib
import os
import re
import socket
import tempfile
import time
from pathlib import Path

__all__ = ["STALE_SECONDS", "TAG", "is_stale", "make_temp", "remove_stale_temps", "temp_prefix"]

#: The word in every temporary file name the project writes.
TAG = "nehad"
#: Age (seconds since the last modification) after which a temporary file whose writer cannot be
#: checked (another machine, or an old-style name) counts as abandoned. A writer in progress
#: touches its file continuously (an encoder) or finishes within seconds (the other writers).
STALE_SECONDS = 3600.0

# .<stem>.nehad-<pid>-<host>-<random>.tmp<suffix>; <host> has only [A-Za-z0-9_] (see _host)
_NEW = re.compile(r"^\.(?P<stem>.*)\." + TAG + r"-(?P<pid>\d+)-(?P<host>[A-Za-z0-9_]+)-"
                  r"[A-Za-z0-9_]+\.tmp(?P<suffix>.*)$")
# tempfile.mkstemp's 8 random characters, before issue 15: .<stem>.<random>.tmp<suffix>
_OLD = re.compile(r"^\.(?P<stem>.*)\.(?P<rand>[a-z0-9_]{8})\.tmp(?P<suffix>.*)$")


def _host() -> str:
    return re.sub(r"[^A-Za-z0-9_]", "_", socket.gethostname())[:40] or "host"


def temp_prefix(path) -> str:
    """The name prefix of this process's temporary files for `path` (before the random part)."""
    return f".{Path(path).stem}.{TAG}-{os.getpid()}-{_host()}-"


def make_temp(path) -> str:
    """Create an empty temporary file for `path` in its folder (named as the module doc says) and
    return its path."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=temp_prefix(path), suffix=f".tmp{path.suffix}",
                               dir=path.parent)
    os.close(fd)
    return tmp


def _pid_alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's live process
        return True
    except OSError:
        return True  # cannot tell: keep the file
    return True


def is_stale(entry: Path, now: float | None = None) -> bool:
    """Whether `entry`, a temporary file name of this module's form, was abandoned (module doc)."""
    name = entry.name
    now = time.time() if now is None else now
    m = _NEW.match(name)
    if m:
        pid = int(m.group("pid"))
        if m.group("host") == _host():
            return pid != os.getpid() and not _pid_alive(pid)
    elif not _OLD.match(name):
        return False
    try:
        age = now - entry.lstat().st_mtime
    except OSError:
        return False
    return age > STALE_SECONDS


def remove_stale_temps(folder, target=None) -> list[Path]:
    """Remove the stale temporary files in `folder` (module doc): those of the file `target`
    (a name or path in that folder), or of any target when it is None. Returns what was removed;
    files that vanish or cannot be removed meanwhile are skipped."""
    folder = Path(folder)
    stem = suffix = None
    if target is not None:
        stem, suffix = Path(target).stem, Path(target).suffix
    removed = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    now = time.time()
    for e in entries:
        if not e.name.startswith(".") or ".tmp" not in e.name:
            continue
        m = _NEW.match(e.name) or _OLD.match(e.name)
        if m is None:
            continue
        if stem is not None and (m.group("stem"), m.group("suffix")) != (stem, suffix):
            continue
        p = Path(e.path)
        with contextlib.suppress(OSError):
            if e.is_file(follow_symlinks=False) and is_stale(p, now):
                p.unlink()
                removed.append(p)
    return removed
