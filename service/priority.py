"""Process priorities: the control path above, background work below.

On a small machine (2 vCPUs here) the loop, the HIL plant and Zenoh's threads share the cores with work that can
wait: the recorder's writer (JSON, zstd, file I/O) and the forecast worker (4-40 ms of closed-loop simulation per
window). At equal priority the scheduler gives them the core at the wrong moment, and the sample arrives, or the
command leaves, a period late. Measured (``energyctl bench realtime``, docs/benchmarks.md): at 1 kHz that was
most of the missed commands.

Linux keeps the nice value per thread and a new thread or process inherits it from the one that creates it, so
``set_nice`` is called first thing in a process's main thread: every thread created afterwards (Zenoh's runtime,
the loop, the query threads) and every process it spawns starts there. The background processes then lower
themselves with ``background`` to at least their fixed level, never above their parent.

**Timer slack.** Linux lets a timed wait of a normal thread (sleep, a timed lock or queue get) end up to the thread's
timer slack late, 50 us by default, so that wake-ups can be coalesced. Measured here (a 60 us sleep, 20 000 times):
50 us slack overshoots by 56 us p50 and 123 us p99.9; 1 us slack by 6.5 us p50 and 72 us p99.9. At 10 kHz the 50 us
is half a period, and a loop can only hit its instants by spinning through it (a whole core, on a machine of two).
``set_timer_slack`` is called next to ``set_nice`` and, like the nice value, is inherited by every thread and process
started afterwards; ``background`` puts the background processes back to the kernel's 50 us.
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys

RECORDER_NICE = 10  # the recorder's writer: it has a 4 s ring (at 10 kHz) to catch up in, so it can wait
FORECAST_NICE = 19  # the forecast worker: a window ahead (hundreds of ms) for a job of 4-40 ms
DEFAULT_TIMER_SLACK_NS = 50_000  # the kernel's default for a normal thread
# a stop signal arms SIGALRM this long ahead (clients.live.install_stop_handlers): a stop that hangs ends by it
STOP_GRACE_S = 5
_PR_SET_TIMERSLACK, _PR_GET_TIMERSLACK = 29, 30  # linux/prctl.h


def _libc(name: str):
    """The C library's function ``name`` (errno kept for ctypes.get_errno), None off Linux or where it has none."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        return getattr(ctypes.CDLL(None, use_errno=True), name)
    except (OSError, AttributeError):
        return None


def _prctl():
    return _libc("prctl")


def timer_slack_ns() -> int | None:
    """The calling thread's timer slack, ns (None where the system has no prctl)."""
    prctl = _prctl()
    return None if prctl is None else int(prctl(_PR_GET_TIMERSLACK, 0, 0, 0, 0))


def set_timer_slack(ns: int | None) -> str | None:
    """Set the calling thread's timer slack to ``ns`` (None or 0: leave it; for the kernel 0 would mean "back to
    the inherited default"). Returns a one-line reason when the system has no such setting or refused, else None.
    Needs no privilege."""
    if not ns:
        return None
    prctl = _prctl()
    if prctl is None:
        return f"cannot set timer slack {ns} ns: no prctl on {sys.platform}"
    if prctl(_PR_SET_TIMERSLACK, ctypes.c_ulong(ns), 0, 0, 0) != 0:
        return f"cannot set timer slack {ns} ns: {os.strerror(ctypes.get_errno())}"
    return None


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


def leave_realtime() -> None:
    """The calling thread back to SCHED_OTHER if it runs SCHED_FIFO or SCHED_RR (lowering needs no privilege;
    where the system has no such call or refuses, it stays as it is)."""
    if not hasattr(os, "sched_getscheduler"):
        return
    try:
        if os.sched_getscheduler(0) in (os.SCHED_FIFO, os.SCHED_RR):
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except OSError:
        pass


def in_normal_thread(fn):
    """fn() run in a new thread at SCHED_OTHER, its result returned (its exception raised): a process spawned
    from there starts at SCHED_OTHER whatever the caller runs at (Linux keeps the policy per thread, and a child
    inherits its forking thread's). A forecast worker spawned from a daemon under chrt -f imported for a second at
    FIFO and starved the daemon's Zenoh threads until its token lapsed."""
    import threading

    out: list = []

    def run() -> None:
        leave_realtime()
        try:
            out.append((True, fn()))
        except BaseException as e:  # noqa: BLE001 - handed to the caller
            out.append((False, e))

    t = threading.Thread(target=run, name="normal-priority", daemon=True)
    t.start()
    t.join()
    ok, value = out[0]
    if not ok:
        raise value
    return value


def background(level: int) -> None:
    """Lower the calling process to nice ``level``, or stay where it is if that is lower already, and give it the
    kernel's default timer slack back (its waits need not be punctual); none of it needs privilege. A process
    started from a realtime one (chrt -f) inherits SCHED_FIFO, which nice does not touch: it is put back to
    SCHED_OTHER too (start such processes from ``in_normal_thread``: this runs only once the child is up)."""
    leave_realtime()
    set_timer_slack(DEFAULT_TIMER_SLACK_NS)
    now = os.getpriority(os.PRIO_PROCESS, 0)
    if level > now:
        os.setpriority(os.PRIO_PROCESS, 0, level)


def hurry(pid: int) -> bool:
    """Give a background child (every thread of it) the caller's own nice value back: a recorder's writer with its
    ring to drain at a stop. At nice 10 beside other work (a busy loop on one of the 2 CPUs) the drain took 3-5 s, and
    the stop's grace (STOP_GRACE_S) ended a clean stop by SIGALRM (exit -14 for the daemon and the
    plant of a 2 kHz stack, 2 of 3 stops).
    Lowering a nice value needs privilege (root, CAP_SYS_NICE or RLIMIT_NICE); without it the child stays where it
    is and this returns False."""
    try:
        own = os.getpriority(os.PRIO_PROCESS, 0)
        tids = [int(t) for t in os.listdir(f"/proc/{pid}/task")] if os.path.isdir(f"/proc/{pid}/task") else [pid]
        for tid in tids:  # Linux: PRIO_PROCESS with an id sets that one thread
            if os.getpriority(os.PRIO_PROCESS, tid) > own:
                os.setpriority(os.PRIO_PROCESS, tid, own)
    except (OSError, ValueError):  # not privileged, or the child (or a thread of it) has just ended
        return False
    return True


def extend_stop_grace(grace_s: int = STOP_GRACE_S) -> None:
    """A stop that is making progress (the recorder's writer still writing the rest of its ring) is not a stop that
    hangs: if a stop's alarm is pending, it fires no sooner than grace_s from now. Without a pending alarm (no stop
    signal came) nothing is armed."""
    left = signal.alarm(0)
    if left:
        signal.alarm(max(left, grace_s))


_PR_SET_PDEATHSIG = 1  # linux/prctl.h
PARENT_ENV = "ENERGYCTL_PARENT"  # "PID" or "PID:watch": a child `energyctl` ends when PID does (die_with_parent)
WATCH_PERIOD_S = 0.25  # how often a watching child looks whether its parent is still there


def die_with_parent(parent: int, forked_by_main_thread: bool = True) -> str:
    """End the calling process with SIGTERM (its own handler, if any, runs: a daemon stops as on a kill) once
    ``parent`` is no longer its parent: it died, SIGKILL included, and the child was handed to init or a subreaper.
    Without this a spawned worker waits on a pipe it holds both ends of, and lives on (a forecast worker of 46 MB and
    the resource tracker it kept alive, 13 MB, outlived a SIGKILLed daemon by more than 9 minutes).

    Linux's PR_SET_PDEATHSIG signals the child when the *thread* that forked it ends, so it is used only when that
    thread was the parent's main thread (``forked_by_main_thread``), which ends only with the process; otherwise
    (a worker started from a short-lived thread: service.priority.in_normal_thread) a daemon thread looks at
    getppid() every WATCH_PERIOD_S. Returns "pdeathsig" or "watch": which one it set up."""
    import signal
    import threading

    how = "watch"
    prctl = _prctl() if forked_by_main_thread else None
    if prctl is not None and prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0) == 0:
        how = "pdeathsig"
    else:
        def watch() -> None:
            import time

            while os.getppid() == parent:
                time.sleep(WATCH_PERIOD_S)
            os.kill(os.getpid(), signal.SIGTERM)

        threading.Thread(target=watch, name="parent-watch", daemon=True).start()
    if os.getppid() != parent:  # it died before the signal was asked for
        os.kill(os.getpid(), signal.SIGTERM)
    return how


def parent_env() -> dict[str, str]:
    """The environment entry that makes a child ``energyctl`` (clients.cli.main) die with this process: started from
    this process's main thread, by PR_SET_PDEATHSIG, else by watching."""
    import threading

    main = threading.current_thread() is threading.main_thread()
    return {PARENT_ENV: f"{os.getpid()}" if main else f"{os.getpid()}:watch"}


def die_with_parent_from_env() -> str | None:
    """In a child ``energyctl``: die_with_parent as parent_env asked (the entry is removed, so that what this process
    starts is not tied to its parent's parent); None when it was not asked."""
    value = os.environ.pop(PARENT_ENV, "")
    pid, _, mode = value.partition(":")
    if not pid.isdigit():
        return None
    return die_with_parent(int(pid), forked_by_main_thread=mode != "watch")


def background_child(level: int, parent: int, forked_by_main_thread: bool) -> None:
    """A background worker's initializer: ``background(level)``, and it ends with its parent (die_with_parent)."""
    background(level)
    die_with_parent(parent, forked_by_main_thread)


def set_cpus(cpus: list[int] | None) -> str | None:
    """Keep the calling thread, and every thread and process it starts afterwards, on ``cpus`` (None: leave it).
    Returns a one-line reason when the system refused or has no such call, else None."""
    if not cpus:
        return None
    if not hasattr(os, "sched_setaffinity"):
        return f"cannot keep to CPUs {cpus}: no sched_setaffinity on {sys.platform}"
    try:
        os.sched_setaffinity(0, set(cpus))
    except OSError as e:
        return f"cannot keep to CPUs {cpus}: {e.strerror}"
    return None


_M_MMAP_THRESHOLD = -3  # malloc.h


def set_mmap_threshold(nbytes: int | None) -> str | None:
    """glibc: serve every block of ``nbytes`` or more by its own mapping, returned to the system when freed, and keep
    that threshold fixed (None or 0: leave glibc's dynamic one, which rises to the size of each such block freed, up
    to 32 MiB; from then on large temporaries come from the thread arenas and their pages stay resident). Measured
    (docs/decisions, the mmap threshold): with it, the daemon's resident size is about 4 MB lower and grows less in
    a soak. Returns a one-line reason when the C library has no mallopt or refused, else None. Needs no privilege."""
    if not nbytes:
        return None
    mallopt = _libc("mallopt")
    if mallopt is None:
        return f"cannot fix the mmap threshold at {nbytes} B: no mallopt on {sys.platform}"
    if mallopt(_M_MMAP_THRESHOLD, ctypes.c_int(nbytes)) != 1:
        return f"cannot fix the mmap threshold at {nbytes} B: mallopt refused"
    return None


TUPLE_FREE_LIST_SIZES = range(1, 21)  # CPython 3.11-3.13 keep freed tuples of lengths 1-20 for reuse,
TUPLE_FREE_LIST_MAX = 2000  # up to 2000 of each length (Objects/tupleobject.c, PyTuple_MAXFREELIST)


def fill_tuple_free_lists() -> None:
    """Fill CPython's tuple free lists now, before the loop runs, instead of over the loop's first ~10 minutes.

    CPython keeps up to 2000 freed tuples of each length 1-20 for reuse; they stay allocated. In the daemon these
    lists grew by a few tuples a second for minutes (measured in a 3 kHz soak with ``sys._debugmallocstats``: the
    17- and 4-long ones +480 each in 2 minutes, one of each per forecast window, and these were exactly the blocks
    that tracemalloc saw as "live" and the Python arena's resident pages that kept growing; docs/decisions, the
    tuple free lists).
    That looked like a leak of ~60 KiB/min and levelled off only when the lists were full. Making 2000 tuples of
    each length and freeing them fills every list at once: ~5 MB up front, no growth afterwards. A list already
    full stays as it is (a tuple freed to a full list goes back to the allocator)."""
    held = [[tuple(range(n)) for _ in range(TUPLE_FREE_LIST_MAX)] for n in TUPLE_FREE_LIST_SIZES]
    del held
