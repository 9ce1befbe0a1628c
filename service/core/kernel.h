/* Shared declarations of the compiled twin (the extension service._kernel), one source per layer:
 *   service/core/kernel.c        the control core's step (ControlCore.step and its estimator): the Kernel type
 *   service/plant/rk4.c          the plant's RK4 integrator (RLCPlant.advance)
 *   service/plant/network.c      a DC network's RK4 integrator (service/plant/network.py steps)
 *   service/daemon/tickwriter.c  the daemon's stepped tick after its checks (TickWriter)
 *   service/kernel_module.c      the module that registers them
 * Built with -ffp-contract=off so that every result is bit-identical to the Python reference.
 */
#ifndef ENERGYCTL_KERNEL_H
#define ENERGYCTL_KERNEL_H
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <string.h>

#define PYMIN(a, b) ((b) < (a) ? (b) : (a))
#define PYMAX(a, b) ((b) > (a) ? (b) : (a))

enum { K_FIXED = 0, K_LQR = 1, K_BM = 2, K_FBLC = 3, K_SMC = 4, K_NESTED = 5, K_PI = 6 };

/* Sequence numbers are integers all the way (a double stops being exact at 2^53): |seq| < SEQ_MAX, so that seq - d - 1
   never overflows. SEQ_NONE marks an empty slot. */
#define SEQ_MAX (1LL << 62)
#define SEQ_NONE (-(1LL << 62) - 1000)

/* Output buffer layout (doubles), shared with service/core/compiled.py; o[O_SEQ] holds the int64 seq's bytes. */
enum {
    O_DU = 0, O_DU_RAW, O_UZ, O_YZ, O_YREF, O_E, O_LIMITED, O_IPRED, O_VPRED, O_UPRED, O_Z0, O_Z1,
    O_SEQ, O_T, O_STEPS, O_COUNT, O_HAS_EST,
    O_EST = 17, /* 18 RLCEnergy fields, in its __slots__ order */
    O_FITV = 35, O_FITS = 38, O_ZRUN0 = 41, O_ZRUN1 = 42, O_DU_NEXT = 43, O_LATE = 44, O_ILIM = 45,
    O_N = 46
};
enum { E_E = 0, E_ET, E_D, E_TAU, E_P, E_PDOT, E_PU, E_QDU, E_PL, E_QDL, E_PM, E_YZ, E_YZB, E_ETA, E_PRO, E_QRO,
       E_PROP, E_QROP };

typedef struct {
    PyObject_HEAD
    /* model and timing */
    double R, L, C, T, tau;
    int d, n_pred;
    /* gains and limits (set_params) */
    int kind, continuous, cancel_Et, plan;
    double v_ref, K, alpha, phi, decay, lK1, lK2, bK1, bK2, bK3, bPi, u_min, u_max, r_max, i_floor, keC, late_tol;
    double obs; /* observer_gain (0: the prediction starts from the raw sample) */
    int load_ref; /* load_power: 1 = -P_in (the neighbours' announced power), 0 = v i_2 measured */
    double nK_P, nK_E, i_max, n_decay; /* nested: branch-power and terminal-energy rates (1/s), current limit (A; 0:
                                          none), exp(-K_u T) */
    double kp_i, ki_i, kp_v, ki_v; /* pi: the current loop's and the voltage loop's gains */
    double pi_xv, pi_xi, pi_u; /* pi: the integrals of the voltage and current errors, the u it asks for (V) */
    int ilim; /* the last law call met the current limit (nested) */
    /* the observer: seq of its last estimate, the estimate (i, v, u) and the load power (W) carried with it */
    long long x_seq;
    double x_hat[3], x_P;
    /* late-command detection: the last step's seq and measured u, and the verdict */
    long long last_seq_u;
    double last_u;
    int late;
    /* estimator: EwLineFit over (i, v, i_2) and the z_out integrals */
    int has_t;
    double t_last, S0, S1, S2, Sy[3], Say[3], ref[3];
    int has_last;
    double last_t, last_P, last_Q;
    /* the last d + 1 samples answered: pending_seq[j] = s, pending[2 j] = du/dt answering s, [2 j + 1] = du/dt
       planned for the period after, at j = s mod (d + 1) (s = SEQ_NONE: none); previous command */
    long long *pending_seq;
    double *pending;
    double r_prev;
    double o[O_N];
} Kernel;

/* ControlCore.step; returns 1 if the estimator took the sample (core/kernel.c). */
int kernel_step(Kernel *k, long long seq, double t, double si_, double sv, double su, double si2, double P_in,
                double P_in_dot);
/* The outgoing rates at the port after a step (core/kernel.c). */
PyObject *port_rates(const double *o, double *qdot);
/* n float arguments of a METH_FASTCALL function into x; 0 with an exception set if they are not that. */
int float_args(PyObject *const *args, Py_ssize_t nargs, int n, double *x, const char *usage);
/* step(seq, t, ...)'s arguments: seq an integer (a float only if integral and below 2^53, as before), |seq| < SEQ_MAX,
   then n - 1 floats into x[1..n-1]; 0 with an exception set if they are not that (core/kernel.c). */
int seq_float_args(PyObject *const *args, Py_ssize_t nargs, int n, long long *seq, double *x, const char *usage);
/* The seq of the last step, from o[O_SEQ] (core/kernel.c). */
long long kernel_seq(const Kernel *k);
/* plant_steps(R, L, C, v_min, u_min, u_max, clip, r, h, n_sub, Pa, dP, ma, dm, i, v, u) (plant/rk4.c). */
PyObject *plant_steps(PyObject *mod, PyObject *const *args, Py_ssize_t nargs);
/* network_steps(h, n_sub, src, r, lines, node_C, loads, i_s, u_s, i_l, v_n) (plant/network.c). */
PyObject *network_steps(PyObject *mod, PyObject *const *args, Py_ssize_t nargs);

extern PyTypeObject KernelType;     /* core/kernel.c */
extern PyTypeObject TickWriterType; /* daemon/tickwriter.c */

#endif
