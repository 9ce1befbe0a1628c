"""Process priorities: the control path above, background work below.

On a small machine (2 vCPUs here) the loop, the HIL plant and Zenoh's threads share the cores with work that can
wait: the recorder's writer (JSON, zstd, file I/O) and the forecast worker (4-40 ms of closed-loop simulation per
window). At equal priority the scheduler gives them the core at the wrong moment, and the sample arrives, or the
command leaves, a period late. Measured (``energyctl bench realtime``, README): at 1 kHz that was most of the
missed commands.

Linux keeps the nice value per thread and a new thread or process inherits it from the one that creates it, so
``set_nice`` is called first thing in a process's main thread: every thread created afterwards (Zenoh's runtime,
the loop, the query threads) and every process it spawns starts there. The background processes then lower
themselves with ``background`` to at least their fixed level, never above their parent.
"""

from __future__ import annotations

import os

RECORDER_NICE = 10  # the recorder's writer: it has a 4 s ring (at 10 kHz) to catch up in, so it can wait
FORECAST_NICE = 19  # the forecast worker: a window ahead (hundreds of ms) for a job of 4-40 ms


def set_nice(target: int | None) -> str | None:
    """Set the calling thread's nice value to ``target`` (None: leave it). Returns a one-line reason when the
    system refused (raising priority needs CAP_SYS_NICE), else None: the caller says it once and goes on."""
    if target is None:
        return None
    now = os.getpriority(os.PRIO_PROCESS, 0)
    if target == now:
        return None
    try:
        os.setpriority(os.PRIO_PROCESS, 0, target)
    except PermissionError:
        return f"cannot set nice {target} (needs CAP_SYS_NICE or a matching RLIMIT_NICE); running at nice {now}"
    return None


def background(level: int) -> None:
    """Lower the calling process to nice ``level``, or stay where it is if that is lower already. Lowering
    priority needs no privilege."""
    now = os.getpriority(os.PRIO_PROCESS, 0)
    if level > now:
        os.setpriority(os.PRIO_PROCESS, 0, level)
