"""What the daemon knows of each neighbour: its newest interaction variable, its announced forecast boxes, its
liveliness; filled by the loop thread only."""

from __future__ import annotations


class Neighbour:
    __slots__ = ("id", "sub", "seq", "t", "P", "P_dot", "Qdot", "rx_ns", "ranges", "count", "topic",
                 "alive", "alive_seen", "lagging")

    def __init__(self, nid: str, sub):
        self.id, self.sub = nid, sub
        self.seq = -1
        self.t = self.P = self.P_dot = self.Qdot = 0.0
        self.rx_ns = 0
        # its announced forecast boxes (P_min, P_max, P_dot_min, P_dot_max) by window parity: (window, box); a
        # message carries the current window's or the next one's (feasibility.announced_window)
        self.ranges: list[tuple[int, tuple]] = [(-1, ()), (-1, ())]
        self.count = 0
        self.topic = ""
        # its liveliness token: None until seen either way, then True/False (the loop polls the token
        # channel in _poll_neighbours); alive_seen is what the loop last logged
        self.alive: bool | None = None
        self.alive_seen: bool | None = None
        self.lagging = False  # lockstep: timed out once; not waited for again until it catches up

    def box(self, window: int) -> tuple | None:
        """Its forecast box for this window, if it announced one."""
        w, b = self.ranges[window & 1]
        return b if w == window else None

    def fresh(self, now_ns: int, stale_ns: int) -> bool:
        """Heard from within stale_ns, and its liveliness token not gone."""
        return self.count > 0 and now_ns - self.rx_ns <= stale_ns and self.alive is not False
