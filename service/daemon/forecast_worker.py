"""The daemon's side of forecasting: Z^{r,out} for the next window runs off the loop thread and off the loop's
GIL, in one spawned worker process at background priority (``service.forecast`` is the pure computation)."""

from __future__ import annotations

import os

from schemas.scenario import CircuitParams, ControllerConfig
from service.forecast import OutgoingForecast, forecast_outgoing, widen_to_grid
from service.priority import FORECAST_NICE, background_child, in_normal_thread, leave_realtime


def _worker_ready() -> bool:
    return True


def start_background_pool():
    """One worker process at background priority, started from a normal-priority thread (service.priority.
    in_normal_thread) and waited for until it has imported everything (about 1 s of CPU: better before a loop runs
    than during it)."""
    def start():
        pool = ForecastWorker._new_pool()
        pool.submit(_worker_ready).result(timeout=60)
        return pool

    return in_normal_thread(start)


def end_pool(pool) -> None:
    """Stop the pool's worker at once: a forecast in flight is moot at a stop, and at nice 19 beside other work a
    job of 40 ms took seconds, past the stop's grace (service.priority.STOP_GRACE_S). CPython's ProcessPoolExecutor
    keeps its workers in ``_processes`` (Python 3.14's ``terminate_workers()`` does the same); the worker holds no
    file, so SIGKILL loses nothing."""
    for p in list((getattr(pool, "_processes", None) or {}).values()):
        p.kill()
    pool.shutdown(wait=True, cancel_futures=True)


class ForecastWorker:
    """Forecasts Z^{r,out}[w] for the newest window the neighbours announced (``request`` from the loop thread:
    stores a tuple and sets an event, never waits). A thread of its own hands the request to one worker process
    and keeps the result in ``result`` ((window, OutgoingForecast), replaced whole) for the loop to publish.
    Forecasts are cached by (widened box, controller)."""

    CACHE = 64

    def __init__(self, model: CircuitParams, period_s: float, delay_samples: int, cfg, window_s: float,
                 quantum: float = 0.02, on_result=None, impl: str = "auto", failure=None, on_failure=None):
        """impl: the core's implementation the forecast's closed loops run (service.core.make_core). failure,
        on_failure: the component's (service.daemon.failure.Failure) and what takes it to its safe state, should this
        thread end by an unexpected exception (without them it is only printed)."""
        import threading

        from service.daemon.failure import Failure, guarded

        self.model, self.period_s, self.delay_samples = model, period_s, delay_samples
        self.impl = impl
        self.cfg, self.window_s, self.quantum = cfg, window_s, quantum
        self.on_result = on_result
        self.result: tuple[int, OutgoingForecast] | None = None
        self.computed = self.cache_hits = self.errors = self.infeasible = 0
        self.last_error = ""
        self.last_ms = 0.0
        self._cache: dict = {}
        self._req: tuple | None = None
        self._ev = threading.Event()
        self._stop = False
        self._pool = None
        self._thread = guarded(failure if failure is not None else Failure("energyctl forecast"), "forecast",
                               self._run, on_failure=on_failure)

    def start(self) -> None:
        """Start the worker process and wait until it has imported everything (about 1 s of CPU: better before
        the loop runs than during its first window)."""
        self._pool = start_background_pool()
        self._thread.start()

    @staticmethod
    def _new_pool():
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        # started from in_normal_thread's short-lived thread: the worker watches its parent (die_with_parent)
        return ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"),
                                   initializer=background_child, initargs=(FORECAST_NICE, os.getpid(), False))

    def request(self, window: int, box: tuple[float, float, float, float], controller: ControllerConfig,
                version: int = 0) -> None:
        """version: the controller config's version (the cache key; a config set bumps it)."""
        self._req = (window, box, controller, version)
        self._ev.set()

    def close(self) -> None:
        self._stop = True
        self._ev.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        if self._pool is not None:
            end_pool(self._pool)
            self._pool = None

    def status(self) -> dict:
        res = self.result
        out: dict = {"computed": self.computed, "cache_hits": self.cache_hits, "infeasible_windows": self.infeasible,
                     "errors": self.errors, "last_error": self.last_error, "last_compute_ms": round(self.last_ms, 2)}
        if res is not None:
            w, f = res
            out.update(window=w, feasible=f.feasible, reason=f.reason,
                       Z_out={"P": [f.P_lo, f.P_hi], "P_dot": [f.P_dot_lo, f.P_dot_hi], "Qdot": [f.Qdot_lo, f.Qdot_hi]},
                       Z_in={"P": list(f.z_in[:2]), "Qdot": list(f.z_in[2:])}, v_range=[f.v_lo, f.v_hi],
                       u_range=[f.u_lo, f.u_hi], limited_ticks=f.limited_ticks)
        return out

    def _run(self) -> None:
        leave_realtime()  # a new worker after a broken one is spawned from this thread: not at the loop's FIFO
        while not self._stop:
            self._ev.wait()
            self._ev.clear()
            req, self._req = self._req, None
            if self._stop or req is None:
                continue
            try:
                self._answer(*req)
            except (ArithmeticError, ValueError) as e:  # a box of finite values beyond the forecast's arithmetic
                self.errors += 1  # (widening 1e308 overflows 2^1024): nobody can forecast it; counted, said
                self.last_error = f"window {req[0]}: box {req[1]}: {type(e).__name__}: {e}"

    def _answer(self, w: int, box: tuple, ctl: ControllerConfig, version: int) -> None:
        import time

        from service.core.control import effective_gain
        from service.core.feasibility import tau_prime

        wide = widen_to_grid(box, self.quantum)
        key = (wide, version)
        tau_p = tau_prime(self.model.L_H, self.model.R_ohm, effective_gain(ctl, self.model))
        f = self._cache.get(key)
        if f is not None:
            self.cache_hits += 1
        else:
            c = self.cfg
            t0 = time.perf_counter()
            try:
                f = self._pool.submit(forecast_outgoing, ctl, self.model, self.period_s, self.delay_samples, wide,
                                      tau_p, steps=c.load_steps, settle_s=c.settle_s,
                                      max_ramp_s=self.window_s, impl=self.impl).result(timeout=60)
            except Exception as e:  # noqa: BLE001 - a broken worker: count, say, start a new one next time
                self.errors += 1
                self.last_error = f"{type(e).__name__}: {e}"
                try:
                    self._pool.shutdown(wait=False, cancel_futures=True)
                finally:
                    self._pool = self._new_pool()
                return
            self.last_ms = (time.perf_counter() - t0) * 1e3
            self.computed += 1
            if len(self._cache) >= self.CACHE:
                self._cache.pop(next(iter(self._cache)))
            self._cache[key] = f
        f = f.for_box(box, tau_p)
        self.infeasible += not f.feasible
        self.result = (w, f)
        if self.on_result is not None:
            self.on_result(w, f)
