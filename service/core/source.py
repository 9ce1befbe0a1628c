"""One network source's controller: the core, and the modes a source on a network needs around it.

The core (``service.core.make_core``) regulates y_z to y_ref = P^{r,in} v_ref / v. On a network three hazards
of the design notes come around it, and this wrapper answers them without touching the law:

* **idle** — y_z = y_ref says nothing about v when P^{r,in} is near zero, and a source that is not connected
  has no power to follow: below ``idle_power_W`` (and whenever it is disconnected) the source holds its voltage
  instead, u -> v_ref - R_droop i with time constant ``idle_tau_s`` (du/dt = (u_target - u) / tau, within the
  slew limit); with ``hold_when_open`` a disconnected one holds u instead, and so does an idle one whose
  interaction variables are stale (its breaker state, which comes with them, is then not known). It leaves idle
  above ``idle_exit`` x that power. The core is told what was applied (``core.hold(seq, du_dt)``), so its delay
  prediction stays right across the switch.
* **stale interaction variables** — when the neighbours' messages are older than the caller's bound
  (``fresh`` False), P^{r,in} falls back: with ``fallback = "last-allocation"`` to the last fresh P^{r,in} it used,
  carried along the change of its own terminal power since (P_own + P^{r,in}_last - P_own at the first stale step):
  its share is kept and a load change is taken up at its terminal, as the own-terminal law does; with
  ``"own-terminal"`` to the source's own terminal power, -v i_out from its own sample alone (the sources then split
  by their lines and v_refs: a source plugged in just before kept 228 of its 600 W, docs/decisions/0032). Following
  its own terminal it idles below ``fallback_idle_power_W`` (default: the idle power), as a source left near zero
  current there rings up the paper law's mapping's fast mode; keeping its share it keeps ``idle_power_W``. Fresh
  again, it
  moves from that power to P^{r,in} linearly over ``resume_ramp_s`` (P = P_own + (P^{r,in} - P_own) n / N, n the
  steps since, N = resume_ramp_s / T): the sources' powers then come back to their shares together, not in a step.
* **light load** is the core's i_floor (``controller.limits.i_floor_A``): the notes measured a 2 A floor
  collapsing a source that carries 200 W; the default 0.5 A does not.

Sign convention (as the core's): P^{r,in} is negative when the source delivers power; a source delivering P W
into its lines has P^{r,in} = -P. Pure: no clocks, no I/O.
"""

from __future__ import annotations

from schemas.scenario import ControllerConfig
from service.core.types import Incoming, Sample

ACTIVE, IDLE, FALLBACK = 0, 1, 2
MODES = ("active", "idle", "fallback")


class SourceController:
    """The core of one source with its idle mode and its stale-data fallback (see the module docstring)."""

    def __init__(self, core, period_s: float, idle_power_W: float = 30.0, idle_exit: float = 1.5,
                 droop_ohm: float = 0.4, idle_tau_s: float = 5e-3, hold_when_open: bool = False,
                 resume_ramp_s: float = 0.0, fallback_idle_power_W: float | None = None,
                 fallback: str = "own-terminal"):
        self.core = core
        if fallback not in ("own-terminal", "last-allocation"):
            raise ValueError(f"fallback: {fallback!r} is not 'own-terminal' or 'last-allocation'")
        self.fallback = fallback
        self._P_last = None  # the last fresh P^{r,in} it used (W): what "last-allocation" keeps
        self._was_fresh = True
        self._P_gap = 0.0  # last-allocation: that P^{r,in} minus its own terminal's power when it went stale
        # disconnected: hold u (du/dt = 0) instead of the droop law; at a low rate with milliseconds of loop delay
        # the droop law cannot damp the open terminal's L-C resonance and rang it up (1 kHz, 2-4 ms: diverged)
        self.hold_when_open = hold_when_open
        self.T = period_s
        self.idle_power_W, self.idle_exit = idle_power_W, idle_exit
        # in fallback: near zero current the mapping's fast mode u/(i L) rang up at 1 kHz (docs/decisions/0027)
        self.fallback_idle_power_W = idle_power_W if fallback_idle_power_W is None else fallback_idle_power_W
        self.droop_ohm, self.idle_tau_s = droop_ohm, idle_tau_s
        self.mode = IDLE
        self.idle = True
        self.P_in_used = 0.0  # the P^{r,in} the last step gave the core (W; its own terminal's in fallback)
        self.resume_steps = max(0, round(resume_ramp_s / period_s))  # N of the resume ramp (0: none)
        self._since_fallback = self.resume_steps  # steps since the last fallback ended (>= N: no ramp)
        self.switches = 0  # entries into and exits from idle

    def reset_fallback(self) -> None:
        """Forget the allocation it would keep: a new run (the rig restarted) allocates afresh, and the previous
        run's share is not this one's."""
        self._P_last, self._P_gap, self._was_fresh = None, 0.0, True
        self._since_fallback = self.resume_steps

    @property
    def v_ref_V(self) -> float:
        return self.core.cfg.v_ref_V

    def set_v_ref(self, v_ref_V: float) -> ControllerConfig | None:
        """Move the voltage reference (the interconnection layer's per-window correction), between two steps; the
        new controller config when it changed (a log records it, so that replay applies it at the same tick)."""
        cfg: ControllerConfig = self.core.cfg
        if v_ref_V == cfg.v_ref_V:
            return None
        new = cfg.model_copy(update={"v_ref_V": v_ref_V})
        self.core.set_gains(new)
        return new

    def step(self, s: Sample, P_in_W: float, P_in_dot_W_per_s: float, connected: bool, fresh: bool
             ) -> tuple[float, float]:
        """(du/dt V/s, planned du/dt for the period after V/s) answering sample s. P_in_W, P_in_dot_W_per_s: the
        incoming interaction variable P^{r,in} (W, negative when delivering) and its rate, as last received;
        connected: its breaker is closed; fresh: that P^{r,in} is recent enough to use. plan, then the core's step
        on what it gives (a live daemon does the two halves itself: its core's step may be the compiled tick)."""
        P, P_dot, r = self.plan(s, P_in_W, P_in_dot_W_per_s, connected, fresh)
        if r is not None:
            return r, 0.0
        out = self.core.step(s, Incoming(P, P_dot))
        return out.du_dt, out.du_dt_next

    def plan(self, s: Sample, P_in_W: float, P_in_dot_W_per_s: float, connected: bool, fresh: bool
             ) -> tuple[float, float, float | None]:
        """What this step does (see step for the arguments): (P^{r,in} W and its rate W/s for the core, None) when
        the core is to step on them, or (P^{r,in} W, 0.0, du/dt V/s) when the source idles: the core was told
        (core.hold) and du/dt is the command. Sets mode, P_in_used and the fallback's state."""
        if not fresh:
            if self.fallback == "last-allocation" and self._P_last is not None:
                P_own = -s.v * s.i_load
                if self._was_fresh:  # its first stale step: what it was asked for against what it delivered
                    self._P_gap = self._P_last - P_own
                P_in_W, P_in_dot_W_per_s = P_own + self._P_gap, 0.0  # its last share kept, the changes followed
            else:
                P_in_W, P_in_dot_W_per_s = -s.v * s.i_load, 0.0  # its own terminal power
            self._since_fallback = 0
        elif self._since_fallback < self.resume_steps:  # back from a fallback: from its own power to P^{r,in}
            self._since_fallback += 1
            a = self._since_fallback / self.resume_steps
            P_own = -s.v * s.i_load
            P_in_W, P_in_dot_W_per_s = P_own + a * (P_in_W - P_own), a * P_in_dot_W_per_s
        self.P_in_used = P_in_W
        self._was_fresh = fresh
        if fresh:
            self._P_last = P_in_W
        power = abs(P_in_W)
        # the fallback floor is the own-terminal law's (near zero current the paper law's mapping rang up): a source
        # keeping its last share keeps the ordinary one (decision 0032)
        floor = self.idle_power_W if fresh or self.fallback == "last-allocation" else self.fallback_idle_power_W
        if not connected:
            idle = True
        elif self.idle:
            idle = power < self.idle_exit * floor
        else:
            idle = power < floor
        if idle != self.idle:
            self.switches += 1
            self.idle = idle
        if idle:
            self.mode = IDLE
            if self.hold_when_open and (not connected or not fresh):
                # open, or not known to be closed: the caller's breaker state comes with the grid sample, and a
                # stale one may say closed after the breaker opened (a host cut off, then tripped)
                self.core.hold(s.seq, 0.0)
                return P_in_W, 0.0, 0.0
            lim = self.core.cfg.limits
            target = self.v_ref_V - self.droop_ohm * s.i
            r = (target - s.u) / self.idle_tau_s
            r = min(max(r, -lim.du_dt_max_V_per_s), lim.du_dt_max_V_per_s)
            self.core.hold(s.seq, r)
            return P_in_W, 0.0, r
        self.mode = ACTIVE if fresh else FALLBACK
        return P_in_W, P_in_dot_W_per_s, None
