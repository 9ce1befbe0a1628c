"""The compiled core: ``service/core/kernel.c`` behind the same interface as ``core.ControlCore``.

The C kernel repeats the Python step operation for operation (see its header), so its du/dt, estimates and
integrals are bit-identical to the reference (tests/core/test_kernel.py). It keeps its outputs in one buffer of
doubles; the views below read them on demand, so a step costs one call, not twenty attribute writes.
``run_batch`` steps a whole replay segment inside C.
"""

from __future__ import annotations

from schemas.scenario import CircuitParams, ControllerConfig
from service._kernel import OUT_LEN, Kernel
from service.core.control import CoreBase
from service.core.energy import RLCEnergy
from service.core.types import Incoming, Sample

KIND_CODE = {"fixed": 0, "lqr": 1, "bm": 2, "fblc": 3, "smc": 4, "nested": 5, "pi": 6}
# output buffer layout: service/core/kernel.h, enum O_*
(O_DU, O_DU_RAW, O_UZ, O_YZ, O_YREF, O_E, O_LIMITED, O_IPRED, O_VPRED, O_UPRED, O_Z0, O_Z1, O_SEQ, O_T, O_STEPS,
 O_COUNT, O_HAS_EST) = range(17)
O_EST, O_FITV, O_FITS, O_ZRUN, O_DU_NEXT, O_LATE, O_ILIM = 17, 35, 38, 41, 43, 44, 45
ROW = 9  # run_batch input row: seq, t, i, v, u, i_load, P_r_in, P_r_in_dot, stepped


def _slot(k: int, doc: str) -> property:
    return property(lambda self: self._b[k], doc=doc)


class KernelEstimate:
    """RLCEnergy's fields (same names, same meaning) read from the kernel's buffer."""

    __slots__ = ("_b",)

    def __init__(self, buf: memoryview):
        self._b = buf


for _j, _name in enumerate(RLCEnergy.__slots__):
    setattr(KernelEstimate, _name, _slot(O_EST + _j, f"RLCEnergy.{_name}"))


class KernelOutput:
    """core.Output's fields read from the kernel's buffer (valid until the next step)."""

    __slots__ = ("_b", "_est", "_q")
    du_dt = _slot(O_DU, "du/dt sent (V/s)")
    du_dt_next = _slot(O_DU_NEXT, "du/dt planned for the period after (V/s; 0 without plan_next_period)")
    du_dt_raw = _slot(O_DU_RAW, "du/dt before limits (V/s)")
    u_z = _slot(O_UZ, "u_z = Qdot^u (W/s)")
    y_z = _slot(O_YZ, "y_z at the sample (W)")
    y_ref = _slot(O_YREF, "y_ref at the sample (W)")
    e = _slot(O_E, "y_z - y_ref (W)")
    i_pred = _slot(O_IPRED, "predicted i at t_{k+d} (A)")
    v_pred = _slot(O_VPRED, "predicted v at t_{k+d} (V)")
    u_pred = _slot(O_UPRED, "predicted u at t_{k+d} (V)")
    z_out0 = _slot(O_Z0, "z_out energy integral (J)")
    z_out1 = _slot(O_Z1, "z_out reactive integral (W)")
    t = _slot(O_T, "sample time (s)")

    def __init__(self, buf: memoryview):
        self._b = buf
        self._est = KernelEstimate(buf)
        self._q = buf.cast("B").cast("q")  # the same bytes as int64s

    @property
    def limited(self) -> bool:
        return self._b[O_LIMITED] != 0.0

    @property
    def late(self) -> bool:
        return self._b[O_LATE] != 0.0

    @property
    def i_limited(self) -> bool:
        return self._b[O_ILIM] != 0.0

    @property
    def seq(self) -> int:  # an int64 in the double buffer's O_SEQ slot (exact above 2^53)
        return self._q[O_SEQ]

    @property
    def est(self) -> KernelEstimate | None:
        return self._est if self._b[O_HAS_EST] != 0.0 else None


class _KernelFit:
    __slots__ = ("_b",)

    def __init__(self, buf: memoryview):
        self._b = buf

    value = property(lambda self: list(self._b[O_FITV:O_FITV + 3]), doc="filtered (i, v, i_2)")
    slope = property(lambda self: list(self._b[O_FITS:O_FITS + 3]), doc="their time derivatives")
    count = property(lambda self: int(self._b[O_COUNT]), doc="samples taken since reset")


class _KernelEstimator:
    __slots__ = ("fit", "_b")

    def __init__(self, buf: memoryview):
        self._b = buf
        self.fit = _KernelFit(buf)

    @property
    def z_out(self) -> list[float]:
        return list(self._b[O_ZRUN:O_ZRUN + 2])


class CompiledCore(CoreBase):
    """ControlCore's interface over the C kernel; bit-identical results."""

    impl = "c"

    def __init__(self, cfg: ControllerConfig, model: CircuitParams, period_s: float,
                 loop_delay_samples: int = 0):
        super().__init__(cfg, model, period_s, loop_delay_samples)
        self._k = Kernel(self._R, self._L, self._C, self.T, cfg.deriv_tau_s, self.d, self.n_pred)
        self._b = memoryview(self._k).cast("d")
        assert len(self._b) == OUT_LEN
        self._push()
        self.out = KernelOutput(self._b)
        self.estimator = _KernelEstimator(self._b)
        self._step = self._k.step
        self.step_values = self._k.step_values
        self.est_record = self._k.est_record
        self.interaction = self._k.interaction

    def _cache(self) -> None:
        super()._cache()
        if hasattr(self, "_k"):
            self._push()

    def _push(self) -> None:
        v_ref, K, cancel_Et, alpha, phi, decay = self._gains
        self._k.set_params(KIND_CODE[self._kind], int(self._continuous), int(bool(cancel_Et)), int(self._plan),
                           (v_ref, K, alpha, phi, decay), self._lqr, self._bm, self._lim, self._keC, self._late_tol,
                           self._obs, int(self._load_ref), self._nested, self._pi[:4])

    def reset(self) -> None:
        self._k.reset()

    @property
    def steps(self) -> int:
        return int(self._b[O_STEPS])

    def applied_rate(self) -> float:
        return self._k.applied_rate()

    def hold(self, seq: int, du_dt: float = 0.0) -> None:
        self._k.hold(seq, du_dt)

    def step(self, s: Sample, inc: Incoming) -> KernelOutput:
        self._step(s.seq, s.t, s.i, s.v, s.u, s.i_load, inc.P_r_in, inc.P_r_in_dot)
        return self.out

    def run_batch(self, rows, du_out, next_out=None) -> None:
        """Step n rows (a C-contiguous n x w array of doubles, w >= 9: seq, t, i, v, u, i_load, P_r_in, P_r_in_dot,
        stepped, then anything) and write each du/dt (0.0 where stepped is 0: not given to the core, held) into
        du_out (n doubles), and the planned du/dt into next_out if given."""
        if next_out is None:
            self._k.run(rows, du_out, rows.shape[1])
        else:
            self._k.run(rows, du_out, rows.shape[1], next_out)
