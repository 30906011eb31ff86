"""Ctrl-C in the `nehad` command (issue 26): taken at a safe point, bounded, explained.

Python raises KeyboardInterrupt at whatever bytecode the main thread runs when SIGINT arrives.
In a training step that is often inside a library: numba calls back into Python four times a
step (``_numba_unpickle`` from its compiled parallel kernels), and a KeyboardInterrupt there comes
back as ``SystemError: ... returned a result with an exception set`` (a traceback instead of
the promised message; reproduced by ``bench/ctrl_c.py``); inside numba's or tqdm's Python-level
lock wrappers it leaves a lock held (acquired, never released) that a thread or an exit handler
waits on later; inside a ``__del__`` it is printed and dropped, and the work goes on.

So :func:`install` (the `nehad` executable calls it first) handles SIGINT itself:

* Inside :func:`deferred` (the training loop), the first Ctrl-C only sets a flag, and the loop
  raises KeyboardInterrupt at its next :func:`check` (between steps), outside any library. A
  step that does not come back within :data:`DEFERRED_SECONDS` gets the KeyboardInterrupt raised
  in the main thread anyway, as before.
* Elsewhere the first Ctrl-C raises KeyboardInterrupt at once, as Python does.
* The first Ctrl-C hands SIGINT back to the kernel: a second Ctrl-C ends the process at once,
  whatever it is doing (no Python code needs to run for it).
* A watchdog thread starts with the first Ctrl-C: if the process is still alive
  :data:`EXIT_SECONDS` later, it prints every thread's stack (faulthandler) and ends the process
  with status 130, so a Ctrl-C never does nothing and a hang says where it was.

:func:`exit_interrupted` is how a command ends after it has said what is kept: flush, then
``os._exit(130)``, without the interpreter's teardown (seconds of garbage collection of torch's
and numba's objects, and exit handlers that wait on threads).
"""

from __future__ import annotations

import contextlib
import ctypes
import faulthandler
import os
import signal
import sys
import threading
import time

__all__ = ["DEFERRED_SECONDS", "EXIT_SECONDS", "check", "deferred", "exit_interrupted", "install",
           "installed"]

#: seconds a deferred Ctrl-C waits for a safe point before it is raised in the main thread
DEFERRED_SECONDS = 5.0
#: seconds after the first Ctrl-C after which the process ends itself (stacks printed first)
EXIT_SECONDS = 20.0

_lock = threading.Lock()
_state = {"installed": False, "deferred": 0, "pending": False, "raised": False, "first": None}


def installed() -> bool:
    return _state["installed"]


def install() -> None:
    """Handle SIGINT as the module doc says (main thread only; a no-op elsewhere or when a
    handler other than Python's default is in place)."""
    if threading.current_thread() is not threading.main_thread():
        return
    if signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        return
    signal.signal(signal.SIGINT, _on_sigint)
    _state["installed"] = True


def _on_sigint(signum, frame):
    # from now on the kernel ends the process on Ctrl-C: a second one works whatever happens
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    _state["first"] = time.monotonic()
    threading.Thread(target=_watchdog, name="nehad-interrupt-watchdog", daemon=True).start()
    with _lock:
        if _state["deferred"] > 0:
            _state["pending"] = True
            return
        _state["raised"] = True
    raise KeyboardInterrupt


def check() -> None:
    """A safe point: raise KeyboardInterrupt if a Ctrl-C is waiting (see :func:`deferred`)."""
    if not _state["pending"]:
        return
    with _lock:
        if _state["raised"]:
            return
        _state["raised"] = True
    raise KeyboardInterrupt


@contextlib.contextmanager
def deferred():
    """Inside the block a Ctrl-C waits for the next :func:`check` (module doc)."""
    with _lock:
        _state["deferred"] += 1
    try:
        yield
    finally:
        with _lock:
            _state["deferred"] -= 1
    check()  # the block ended before reaching a safe point with the Ctrl-C waiting


def _raise_in_main_thread() -> None:
    ident = threading.main_thread().ident
    ctypes.pythonapi.PyThreadState_SetAsyncExc(ctypes.c_ulong(ident),
                                               ctypes.py_object(KeyboardInterrupt))


def _watchdog() -> None:
    start = _state["first"] or time.monotonic()
    while True:
        time.sleep(0.1)
        waited = time.monotonic() - start
        if waited >= EXIT_SECONDS:
            break
        if waited >= DEFERRED_SECONDS and _state["pending"]:
            with _lock:
                late = not _state["raised"]
                _state["raised"] = True
            if late:
                _raise_in_main_thread()
    try:
        sys.stderr.flush()
    except Exception:  # noqa: BLE001 - the stream may be gone; the message below is raw
        pass
    os.write(2, f"interrupted: still running {EXIT_SECONDS:g} s after Ctrl-C; stopping now. "
                f"Where each thread was:\n".encode())
    faulthandler.dump_traceback(file=sys.__stderr__, all_threads=True)
    os._exit(130)


def exit_interrupted(code: int = 130):
    """End the command after an interruption (module doc): flush the output streams, then leave
    at once when :func:`install` is in force (the `nehad` executable), else ``sys.exit``."""
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    if _state["installed"]:
        os._exit(code)
    sys.exit(code)
