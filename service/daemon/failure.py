"""When a worker thread of a component (the daemon's loop, the coordinator's, the rig's, the bridge's) ends by an
exception nobody expected: the component fails, visibly, instead of running on without it.

Python prints such an exception ("Exception in thread loop") and ends the thread, and the process stays up: a daemon
without its loop still answered status as ``active``, a converter left with no controller. A thread started with
``guarded`` (or a loop that calls ``Failure.record`` itself) hands its exception to the component's ``Failure``: the
first one is kept as the reason (the thread, the exception, where it was raised), printed with its traceback, and
``on_failure`` takes the component to its safe state; the component's status then says ``failed`` with the reason,
and its command exits non-zero (``EXIT_FAILED``).
"""

from __future__ import annotations

import sys
import threading
import traceback

EXIT_FAILED = 1  # the exit status of a command whose component failed (docs/operations.md)


class Failure:
    """The first unexpected exception of a component's threads. ``reason`` is '' until then; ``event`` is set then."""

    def __init__(self, who: str, log=sys.stderr):
        self.who, self.log = who, log
        self.reason = ""
        self.event = threading.Event()
        self._lock = threading.Lock()

    def __bool__(self) -> bool:
        return self.event.is_set()

    def record(self, where: str, exc: BaseException) -> bool:
        """Keep and print the failure of ``where`` (a thread's name); True for the first one, the one that counts."""
        tb = traceback.extract_tb(exc.__traceback__)
        at = f" (at {tb[-1].filename.rsplit('/', 1)[-1]}:{tb[-1].lineno} in {tb[-1].name})" if tb else ""
        reason = f"{where}: {type(exc).__name__}: {exc}{at}"[:500]
        with self._lock:
            first = not self.event.is_set()
            if first:
                self.reason = reason
        text = "".join(traceback.format_exception(exc)).rstrip()
        try:
            print(f"{self.who}: failed: {reason}\n{text}", file=self.log, flush=True)
        except (OSError, ValueError):  # a closed log: the reason is still in status
            pass
        self.event.set()
        return first


def guarded(failure: Failure, name: str, target, *args, on_failure=None) -> threading.Thread:
    """A daemon thread running target(*args); an exception out of it is ``failure.record``-ed and, the first time,
    ``on_failure()`` is called (on that thread) to take the component to its safe state."""

    def run() -> None:
        try:
            target(*args)
        except BaseException as e:  # noqa: BLE001 - whatever ended it: the component fails, visibly
            if failure.record(name, e) and on_failure is not None:
                on_failure()

    return threading.Thread(target=run, name=name, daemon=True)
