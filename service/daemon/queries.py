"""The daemon's queryables: ``status``, ``config`` and ``config/set``, each answered on its own thread on the
queryable's own key. A config set is validated here and handed to the loop, which applies it between two ticks;
nothing here runs on the loop thread."""

from __future__ import annotations

import json
import sys
import threading
import time

import numpy as np
from pydantic import ValidationError

from schemas.codec import CMD, MEAS
from schemas.scenario import ControllerConfig, ScenarioError, apply_overrides, format_validation_error
from service import __version__
from service.core.delay import loop_delay_report
from service.daemon.bus import key
from service.daemon.loop_stats import HIST

LOOP_DELAY_EVERY_NS = 1_000_000_000  # status queries re-estimate the loop delay at most this often
REFUSED_EVENT_EVERY_NS = 1_000_000_000  # at most one recorded event and stderr line per this (all are counted)


ERROR_TEXT_MAX = 300  # a refusal quotes at most this much of what it refuses (never the request back)


def brief(text: str, limit: int = ERROR_TEXT_MAX) -> str:
    """An error text cut to ``limit`` characters, saying how long it was: a refusal names the field and why, and never
    echoes a large value back."""
    return text if len(text) <= limit else f"{text[:limit]}... [{len(text)} characters, cut]"


class DaemonQueries:
    """The query side of ``Daemon`` (a mixin: it reads the daemon's state, and writes only ``_pending`` and its
    count of refused config requests)."""

    config_refused = 0  # config/set requests (and sets sent to config) answered with an error
    last_config_refused = ""
    _refused_shown: tuple[int | None, int] = (None, 0)  # (monotonic ns of the last event/line, refusals since)
    _refused_lock = threading.Lock()

    def _refused(self, what: str, error: str) -> None:
        """A config request answered with an error: counted, and, at most once per REFUSED_EVENT_EVERY_NS (saying
        how many it stands for), one stderr line and a ``config_refused`` event in the log. Runs on a query
        thread, never the loop's."""
        text = f"{what}: {error}"
        now = time.monotonic_ns()
        with self._refused_lock:
            self.config_refused += 1
            self.last_config_refused = text
            last, held = self._refused_shown
            if last is not None and 0 <= now - last < REFUSED_EVENT_EVERY_NS:
                self._refused_shown = (last, held + 1)
                return
            self._refused_shown = (now, 0)
        if held:
            text = f"{text} [and {held} more since the last of these]"
        print(f"energyctl[{self.cfg.id}]: refused {text} ({self.config_refused} refused so far)", file=sys.stderr,
              flush=True)
        rec = self.recorder
        if rec is not None:
            t = self.last_sample[1] if self.last_sample else 0.0
            rec.offer(self.t_ev, t, (t, max(self._last_seq, 0), "config_refused", text))

    def status(self) -> dict:
        now = time.monotonic_ns()
        est = self.core.out.est
        c = self.cfg
        ls = self.last_sample
        return {
            "id": c.id, "version": __version__, "state": "failed" if self.failure else self.state,
            "failure": self.failure.reason, "config_version": self.config_version,
            "loop": {"rate_hz": c.loop.rate_hz, "trigger": c.loop.trigger,
                     **self.stats.summary(now, fresh=self.state == "shutdown"),
                     # samples the full queue dropped (oldest first) while the loop thread was held up
                     "meas_queue_dropped": getattr(getattr(self, "meas_q", None), "dropped", 0),
                     # frames the loop passed over to answer the newest loop.catch_up (after a wait or a stall)
                     "meas_skipped": self.meas_skipped},
            "last_sample": dict(zip(MEAS.fields, ls, strict=True)) if ls else None,
            "last_command": dict(zip(CMD.fields, self.last_cmd, strict=True)) if self.last_cmd else None,
            "estimate": {k: getattr(est, k) for k in ("E", "E_t", "p", "y_z", "y_z_balance", "eta", "P_r_out_port",
                                                      "Qdot_r_out_port")} if est else None,
            "z_out": list(self.core.estimator.z_out),
            "y_ref": self.core.out.y_ref, "u_z": self.core.out.u_z,
            "neighbours": {nb.id: {"messages": nb.count, "age_s": max(0, now - nb.rx_ns) / 1e9 if nb.count else None,
                                   "fresh": nb.fresh(now, int(c.neighbour_stale_s * 1e9)), "alive": nb.alive,
                                   "lagging": nb.lagging,
                                   "P_r_out": nb.P} for nb in self.neighbours},
            "feasibility": {"violations": self.feas.count, "tau_prime_s": self._tau_p,
                            "recent": [v.__dict__ for v in self.feas.violations],
                            "forecast": self.forecaster.status() if self.forecaster is not None else None},
            "rejected": self._rejected_counts(), "last_reject": self.last_reject,
            "config_refused": self.config_refused, "last_config_refused": self.last_config_refused,
            "clock_resyncs": self.clock_resyncs, "recovery_ticks": self.recovery_ticks,
            "refused_requests": self.refused_requests,
            "reference": self.reference, "degraded_reason": self.degraded_reason if self.state == "degraded" else "",
            "plant_restarts": self.restarts,
            "late_command_ticks": self.late_ticks,
            "current_limited_ticks": self.current_limited_ticks,
            "loop_delay": self._loop_delay(),
            "logging": self._logging_status(),
        }

    def _rejected_counts(self) -> dict[str, int]:
        """The loop's rejections and those refused on receipt (Daemon._admit), by reason."""
        out = dict(self.rejected)
        for k, n in list(self.rx_rejected.items()):
            out[k] = out.get(k, 0) + n
        return out

    def _loop_delay(self) -> dict:
        """The loop delay measured over this plant epoch's newest ticks (service/core/delay.py), against the delay the
        core compensates; read while the loop writes, so a sample at the edge may be torn (a diagnostic, not a
        control input). The estimate takes ~0.4 ms of numpy, mostly holding the GIL the loop needs, so a status
        query reuses one younger than LOOP_DELAY_EVERY_NS (the final status after shutdown is always fresh)."""
        now = time.monotonic_ns()
        cached = self._loop_delay_cache
        if cached is not None and now - cached[0] < LOOP_DELAY_EVERY_NS and self.state != "shutdown":
            return cached[1]
        out = self._estimate_loop_delay()
        self._loop_delay_cache = (now, out)
        return out

    def _estimate_loop_delay(self) -> dict:
        last = self._last_seq
        if last < 0:
            return {"measured_samples": None, "compensated_samples": self.core.d, "mismatch": False, "window": 0}
        seqs = np.arange(max(0, last - HIST + 1), last + 1)  # this plant epoch's newest ticks, oldest first
        idx = seqs & (HIST - 1)
        hist_seq = np.frombuffer(self._hist_seq, dtype=np.int64)
        idx = idx[hist_seq[idx] == seqs]  # slots still holding this epoch's tick of that seq
        return loop_delay_report(hist_seq[idx], np.frombuffer(self._hist_u)[idx], np.frombuffer(self._hist_r)[idx],
                                 self.period_s, self.core.d)

    def _logging_status(self) -> dict | None:
        rec = self.recorder
        if rec is None:  # no log asked for, or a recorder that could not even start
            return {"path": self.log_path, "written": 0, "drops": {}, "state": "degraded",
                    "error": self.log_error} if self.log_error else None
        out = {"path": self.log_path, "written": rec.written, "drops": dict(rec.drops),
               "state": "degraded" if rec.failed else "ok", "error": rec.error}
        if getattr(rec, "close_s", None) is not None:  # after the stop: what the writer had left, how long it took
            out["backlog_at_close"], out["close_s"] = rec.backlog_at_close, round(rec.close_s, 3)
        return out

    def _status_reply(self, query) -> tuple[bool, dict]:
        return True, self.status()

    def _config_reply(self, query) -> tuple[bool, dict]:
        if query.payload is not None or "set" in str(query.parameters).split(";")[0].split("&"):
            where = key(self.cfg.prefix, self.cfg.id, "config/set")
            self._refused("config", f"read-only here; sets go to {where}")
            return False, {"error": f"config is read-only here; sets go to {where}"}
        return True, {"controller": self.core.cfg.model_dump(), "state": self.state,
                      "config_version": self.config_version}

    def _config_set_reply(self, query) -> tuple[bool, dict]:
        limit = self.cfg.query_max_bytes
        p = query.payload
        try:
            size = len(p) if p is not None else 0  # a Zenoh payload's length, without taking its bytes
        except TypeError:  # a payload that does not tell it: its bytes, still before they are parsed
            size = len(p.to_bytes())
        if size > limit:  # measured before it is read: not parsed, not validated, not echoed
            self.refused_requests += 1
            ok, body = False, {"error": f"a request of {size} bytes, above query_max_bytes = {limit}; not read"}
        else:
            try:
                ok, body = self._config_set(query)
            except Exception as e:  # noqa: BLE001 - whatever the request made fail: refused, briefly
                ok, body = False, {"error": f"set: {type(e).__name__}: {e}"}
        if not ok:  # every refusal counted and logged once here (config_refused), its text never the request
            body = {"error": brief(str(body.get("error", "")))}
            self._refused("config/set", body["error"])
        return ok, body

    def _config_set(self, query) -> tuple[bool, dict]:
        try:
            req = json.loads(query.payload.to_bytes()) if query.payload is not None else {}
            sets = req.get("set") if isinstance(req, dict) else None
            if not isinstance(sets, list) or not sets or not all(isinstance(x, str) for x in sets):
                raise ScenarioError("set: expected a non-empty list of 'key=value' strings, as {\"set\": [...]}")
        except (ValueError, ScenarioError, RecursionError) as e:
            ok, body = False, {"error": str(e) if not isinstance(e, RecursionError) else "set: nested too deeply"}
        else:
            ok, body = self.apply_sets(sets)
        return ok, body

    def apply_sets(self, sets: list[str]) -> tuple[bool, dict]:
        """Validate ``controller.X=value`` / ``lifecycle=active|inactive`` and hand them to the loop."""
        if self.failure:
            return False, {"error": f"the loop failed, nothing can be set: {self.failure.reason}"}
        ctl = [s for s in sets if not s.startswith("lifecycle=")]
        life = [s.split("=", 1)[1].strip().strip('"') for s in sets if s.startswith("lifecycle=")]
        if life and life[-1] not in ("active", "inactive"):
            return False, {"error": f"lifecycle: {life[-1]!r} is not one of active, inactive"}
        bad = [s for s in ctl if not s.startswith("controller.")]
        if bad:
            return False, {"error": f"only controller.* and lifecycle can be set at run time: {bad}"}
        try:
            data = apply_overrides({"controller": self.core.cfg.model_dump()}, ctl)["controller"]
            new = ControllerConfig.model_validate(data)
        except ScenarioError as e:
            return False, {"error": str(e)}
        except ValidationError as e:
            return False, {"error": format_validation_error(e, "set", what="config")}
        if new.kind != self.core.cfg.kind or new.mapping != self.core.cfg.mapping:
            return False, {"error": "controller.kind and controller.mapping cannot change at run time"}
        if life:
            self._pending_state = life[-1]
        if ctl:
            ev = threading.Event()
            self._pending = (new, ev, new.model_dump_json())
            if not ev.wait(2.0):
                return False, {"error": "not applied: the loop did not tick within 2 s"}
        print(f"energyctl[{self.cfg.id}]: config set {brief(str(sets))} -> version {self.config_version}",
              file=sys.stderr)
        return True, {"applied": sets, "config_version": self.config_version, "controller": self.core.cfg.model_dump()}
