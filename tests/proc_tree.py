"""The process tree below a pid, from /proc (the test watchdogs of conftest.py). Run as a script it is the session's
guard: ``python proc_tree.py PID`` polls PID's tree every 2 s and, once PID is gone, kills what was below it last."""

from __future__ import annotations

import os
import signal
import sys
import time


def _table() -> dict[int, list[tuple[int, bytes]]]:
    """ppid -> [(pid, state)] of every process (those that vanish while read are left out)."""
    kids: dict[int, list[tuple[int, bytes]]] = {}
    for d in os.listdir("/proc") if os.path.isdir("/proc") else ():
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat", "rb") as f:
                    fields = f.read().rsplit(b")", 1)[1].split()
                kids.setdefault(int(fields[1]), []).append((int(d), fields[0]))
            except (OSError, ValueError, IndexError):
                pass
    return kids


def below(root: int, skip: tuple[int, ...] = ()) -> list[int]:
    """Every pid below root, those in skip (and their subtrees) left out."""
    kids, out, todo = _table(), [], [root]
    while todo:
        for pid, _ in kids.get(todo.pop(), ()):
            if pid not in skip:
                out.append(pid)
                todo.append(pid)
    return out


def alive(pid: int) -> bool:
    """pid exists and is not a zombie."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            return f.read().rsplit(b")", 1)[1].split()[0] != b"Z"
    except (OSError, IndexError):
        return False


def command(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read().replace(b"\0", b" ").decode(errors="replace").strip()
    except OSError:
        return ""


def guard(root: int) -> None:
    last: list[int] = []
    while alive(root):
        last = below(root, (os.getpid(),))
        time.sleep(2.0)
    for pid in last:
        try:
            os.kill(pid, signal.SIGKILL)
        except OSError:
            pass


if __name__ == "__main__":
    guard(int(sys.argv[1]))
