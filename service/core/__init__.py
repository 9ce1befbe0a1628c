"""The pure control core: samples in, command and diagnostics out; no clocks, no I/O, no globals.

Every driver (the offline simulator ``service.sim``, the Zenoh daemon ``service.daemon``, log replay
``service.replay``) builds its core with :func:`make_core` and steps it the same way, so the same inputs give
bit-identical outputs. Two implementations satisfy :class:`Core`: ``control.ControlCore`` (Python, the
reference) and ``compiled.CompiledCore`` (``service/core/kernel.c``, its operation-for-operation twin).
The caller chooses which; nothing here reads the environment.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from schemas.scenario import CircuitParams, ControllerConfig

from .control import ControlCore, CoreBase, core_metadata, effective_gain
from .types import Incoming, Sample

IMPLS = ("auto", "c", "python")

__all__ = ["IMPLS", "Core", "ControlCore", "CoreBase", "Incoming", "Sample", "compiled_available", "core_metadata",
           "effective_gain", "make_core"]


@runtime_checkable
class Core(Protocol):
    """One controller for one source component, stepped once per sample.

    ``step(sample, incoming)`` reads the measured (i A, v V, u V, i_load A) at t s and the incoming interaction
    variable (P^{r,in} W, dP^{r,in}/dt W/s), updates the state it owns and returns the voltage-rate command
    du/dt (V/s) with diagnostics (``out``: y_z W, y_ref W, u_z W/s, the estimate E J, p W, E_t J, eta W ...)."""

    impl: str
    cfg: ControllerConfig
    d: int

    def step(self, s: Sample, inc: Incoming): ...

    def hold(self, seq: int) -> None: ...

    def reset(self) -> None: ...

    def set_gains(self, cfg: ControllerConfig) -> None: ...

    def run_batch(self, rows, du_out, next_out=None) -> None: ...

    def step_values(self, seq: int, t: float, i: float, v: float, u: float, i_load: float, P_r_in: float,
                    P_r_in_dot: float) -> tuple: ...

    def est_record(self) -> tuple: ...

    def interaction(self) -> tuple: ...


def compiled_available() -> bool:
    """Whether the compiled twin (service._kernel) was built at install."""
    try:
        from . import compiled  # noqa: F401
    except ImportError:
        return False
    return True


def make_core(cfg: ControllerConfig, model: CircuitParams, period_s: float, loop_delay_samples: int = 0,
              impl: str | None = "auto") -> Core:
    """The core every driver uses. impl: "c" (the compiled twin, bit-identical), "python" (the reference), or
    "auto" (None too: "c" if it was built, else "python"). period_s: the sample period T (s);
    loop_delay_samples: samples between a measurement and the period its command acts in."""
    impl = impl or "auto"
    if impl not in IMPLS:
        raise ValueError(f"core implementation {impl!r}: expected one of {', '.join(IMPLS)}")
    if impl != "python":
        try:
            from .compiled import CompiledCore
        except ImportError as e:
            if impl == "c":
                raise ImportError(f"the compiled core (service._kernel) is not built: {e}") from e
        else:
            return CompiledCore(cfg, model, period_s, loop_delay_samples)
    return ControlCore(cfg, model, period_s, loop_delay_samples)
