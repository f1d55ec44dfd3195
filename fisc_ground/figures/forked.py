"""A function call in a forked second process, its result collected later: the second core of a
2-core machine for work that is independent of what this process does meanwhile (the paper
companion run of ``fisc-sim run``, half of a run's figures).

``fork`` copies this process, so nothing is imported again and the call's arguments are not
pickled; only the result comes back through a pipe.  Where ``fork`` is unsafe or unavailable (not
Linux, or inside a daemonic worker process such as a sweep's) ``can_fork`` is False and callers
do the work here instead; the results are the same either way.
"""

from __future__ import annotations

import multiprocessing
import sys
import traceback
from collections.abc import Callable
from typing import Any


def can_fork() -> bool:
    """Whether a ``ForkedCall`` may be started here."""
    return (sys.platform == "linux" and "fork" in multiprocessing.get_all_start_methods()
            and not multiprocessing.current_process().daemon)


def _child(fn: Callable[..., Any], args: tuple, send) -> None:
    # the parent's stdout/stderr may be wrapped by a progress display whose lock another thread
    # held at the fork: write to the plain streams instead
    sys.stdout, sys.stderr = sys.__stdout__, sys.__stderr__
    try:
        send.send(("ok", fn(*args)))
    except BaseException as exc:  # noqa: BLE001 - everything is reported to the parent, which raises it
        text = traceback.format_exc()
        try:
            send.send(("error", exc, text))
        except Exception:  # noqa: BLE001 - an exception that does not pickle: its traceback suffices
            send.send(("error", None, text))
    finally:
        send.close()


class ForkedCall:
    """``fn(*args)`` running in a forked process from construction on; ``result()`` waits for it.

    An exception raised there is raised again by ``result()`` (with the other process's traceback
    as a note), or a ``RuntimeError`` carrying that traceback if it does not pickle."""

    def __init__(self, fn: Callable[..., Any], *args: Any, name: str = "fisc-forked") -> None:
        ctx = multiprocessing.get_context("fork")
        self._recv, send = ctx.Pipe(duplex=False)
        self._proc = ctx.Process(target=_child, args=(fn, args, send), name=name, daemon=True)
        self._proc.start()
        send.close()

    def result(self) -> Any:
        """The call's return value (blocks until the process has sent it)."""
        try:
            msg = self._recv.recv()
        except EOFError:
            self._proc.join()
            raise RuntimeError(f"the forked process {self._proc.name} ended without a result "
                               f"(exit code {self._proc.exitcode})") from None
        finally:
            self._recv.close()
        self._proc.join()
        if msg[0] == "ok":
            return msg[1]
        _, exc, text = msg
        if exc is None:
            raise RuntimeError(f"in the forked process {self._proc.name}:\n{text}")
        exc.add_note(f"raised in the forked process {self._proc.name}:\n{text}")
        raise exc

    def cancel(self) -> None:
        """Stop the process (SIGKILL: nothing to clean up there, and it passes any SIGTERM handler
        inherited from this process) and wait for it."""
        self._proc.kill()
        self._proc.join()
        self._recv.close()
