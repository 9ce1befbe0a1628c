#include "kernel.h"

/* TickWriter: what service/daemon/daemon.py's _tick does with a stepped sample once its checks passed and P^{r,in} is
 * formed (its Python lines for the Python core are the reference; tests/daemon/test_tickwriter.py checks the bytes are the
 * same): the kernel's step, the command payload (schemas/codec.py CMD), the loop-delay history entry (seq, measured
 * u, du/dt), and the recorder's grouped slot of meas, z_in and cmd (service/logio/ring.py RingRecorder.offer_group,
 * group 0), in one call. The layouts are checked against the codecs' struct formats at construction. */

#define MEAS_FORMAT "<BBQddddd"
#define CMD_FORMAT "<BBQdddB"
#define GROUP_FORMAT "<BdQdddddQdddBQdddB"
enum { MEAS_SIZE = 50, CMD_SIZE = 35, GROUP_SIZE = 123, RING_HDR = 24, RING_SLOT = 128, RING_FAILED = 17 };

typedef struct {
    PyObject_HEAD
    Kernel *k;
    Py_buffer hseq, hu, hr, ring, widx;
    int has_ring;
    long long slots, hist_mask;
    unsigned char cmd_magic, version, group_id, meas_magic;
    int has_meas;  /* accept() configured */
    double v_min, v_max, i_max;
    unsigned long long seq_limit;  /* accept(): seq < seq_limit, t_min <= t < t_limit (schemas.codec MEAS.ranges) */
    double t_min, t_limit;
    double u_max;            /* accept(): |u| <= u_max */
    long long max_gap;       /* accept(): seq - last_seq <= max_gap (samples) */
    double period, clock_tol; /* accept(): |(t - last_t) - (seq - last_seq) * period| <= clock_tol */
} TickWriter;

static void put_u64(unsigned char *p, uint64_t q) { memcpy(p, &q, 8); }
static void put_f64(unsigned char *p, double x) { memcpy(p, &x, 8); }

static void TickWriter_release(TickWriter *self)
{
    if (self->hseq.obj) PyBuffer_Release(&self->hseq);
    if (self->hu.obj) PyBuffer_Release(&self->hu);
    if (self->hr.obj) PyBuffer_Release(&self->hr);
    if (self->ring.obj) PyBuffer_Release(&self->ring);
    if (self->widx.obj) PyBuffer_Release(&self->widx);
    self->has_ring = 0;
}

/* TickWriter(kernel, hist_seq, hist_u, hist_r, cmd_format, cmd_magic, version, ring=None, ring_index=None, slots=0,
 *            group_id=0, group_format="", meas_format="", meas_magic=0, v_min=0, v_max=0, i_max=0,
 *            seq_limit=2^53, t_min=0, t_limit=2^32, u_max=inf, max_gap=2^62, period=0, clock_tol=inf);
 *            seq_limit at most 2^62 (seq is an int64 here) */
static int TickWriter_init(TickWriter *self, PyObject *args, PyObject *kw)
{
    static char *names[] = {"kernel", "hist_seq", "hist_u", "hist_r", "cmd_format", "cmd_magic", "version", "ring",
                            "ring_index", "slots", "group_id", "group_format", "meas_format", "meas_magic", "v_min",
                            "v_max", "i_max", "seq_limit", "t_min", "t_limit", "u_max", "max_gap", "period",
                            "clock_tol", NULL};
    PyObject *kern, *hs, *hu, *hr, *ring = Py_None, *widx = Py_None;
    const char *cmd_fmt, *group_fmt = "", *meas_fmt = "";
    int magic, version, group_id = 0, meas_magic = 0;
    long long slots = 0;
    double v_min = 0.0, v_max = 0.0, i_max = 0.0, t_min = 0.0, t_limit = 4294967296.0;
    unsigned long long seq_limit = 1ULL << 53;
    double u_max = HUGE_VAL, period = 0.0, clock_tol = HUGE_VAL;
    long long max_gap = 1LL << 62;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "O!OOOsii|OOLissidddKdddLdd", names, &KernelType, &kern, &hs, &hu,
                                     &hr, &cmd_fmt, &magic, &version, &ring, &widx, &slots, &group_id, &group_fmt,
                                     &meas_fmt, &meas_magic, &v_min, &v_max, &i_max, &seq_limit, &t_min, &t_limit,
                                     &u_max, &max_gap, &period, &clock_tol))
        return -1;
    TickWriter_release(self);
    if (strcmp(cmd_fmt, CMD_FORMAT) != 0) {
        PyErr_Format(PyExc_ValueError, "TickWriter: the command layout is %s, compiled for " CMD_FORMAT, cmd_fmt);
        return -1;
    }
    self->has_meas = meas_fmt[0] != 0;
    if (self->has_meas && strcmp(meas_fmt, MEAS_FORMAT) != 0) {
        PyErr_Format(PyExc_ValueError, "TickWriter: the measurement layout is %s, compiled for " MEAS_FORMAT, meas_fmt);
        return -1;
    }
    self->meas_magic = (unsigned char)meas_magic;
    self->v_min = v_min; self->v_max = v_max; self->i_max = i_max;
    if (seq_limit > (unsigned long long)SEQ_MAX) {  /* step() carries seq as an integer below 2^62 */
        PyErr_Format(PyExc_ValueError, "TickWriter: seq_limit %llu above 2^62", seq_limit);
        return -1;
    }
    self->seq_limit = seq_limit; self->t_min = t_min; self->t_limit = t_limit;
    self->u_max = u_max; self->max_gap = max_gap; self->period = period; self->clock_tol = clock_tol;
    if (PyObject_GetBuffer(hs, &self->hseq, PyBUF_WRITABLE) < 0 || PyObject_GetBuffer(hu, &self->hu, PyBUF_WRITABLE)
        < 0 || PyObject_GetBuffer(hr, &self->hr, PyBUF_WRITABLE) < 0)
        return -1;
    long long n = self->hseq.len / 8;
    if (n < 1 || (n & (n - 1)) || self->hu.len != n * 8 || self->hr.len != n * 8) {
        PyErr_SetString(PyExc_ValueError, "TickWriter: three histories of one power-of-two length of 8-byte items");
        return -1;
    }
    self->hist_mask = n - 1;
    if (ring != Py_None) {
        if (strcmp(group_fmt, GROUP_FORMAT) != 0) {
            PyErr_Format(PyExc_ValueError, "TickWriter: the recorder group layout is %s, compiled for " GROUP_FORMAT,
                         group_fmt);
            return -1;
        }
        if (PyObject_GetBuffer(ring, &self->ring, PyBUF_WRITABLE) < 0 ||
            PyObject_GetBuffer(widx, &self->widx, PyBUF_WRITABLE) < 0)
            return -1;
        if (slots < 1 || self->ring.len < RING_HDR + slots * RING_SLOT || self->widx.len != 8) {
            PyErr_SetString(PyExc_ValueError, "TickWriter: ring shorter than its slots, or index not one int64");
            return -1;
        }
        self->has_ring = 1;
    }
    Py_INCREF(kern);
    Py_XSETREF(self->k, (Kernel *)kern);
    self->slots = slots;
    self->cmd_magic = (unsigned char)magic;
    self->version = (unsigned char)version;
    self->group_id = (unsigned char)group_id;
    return 0;
}

static void TickWriter_dealloc(TickWriter *self)
{
    TickWriter_release(self);
    Py_XDECREF(self->k);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* step(seq, t, i, v, u, i_load, P_r_in, P_r_in_dot) -> (command payload, du_dt, du_dt_next, limited, late,
 * P_r_out_port or None, Qdot_r_out_port, dropped: the ring was full) */
static PyObject *TickWriter_step(TickWriter *self, PyObject *const *args, Py_ssize_t nargs)
{
    double x[8];
    long long seq;  /* an integer all the way: the command answers exactly the sample's seq */
    if (!seq_float_args(args, nargs, 8, &seq, x, "step(seq, t, i, v, u, i_load, P_r_in, P_r_in_dot)"))
        return NULL;
    if (seq < 0) {
        PyErr_SetString(PyExc_ValueError, "TickWriter.step: seq < 0");
        return NULL;
    }
    if (self->k == NULL || self->hseq.obj == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "TickWriter: released");
        return NULL;
    }
    Kernel *k = self->k;
    kernel_step(k, seq, x[1], x[2], x[3], x[4], x[5], x[6], x[7]);
    const double *o = k->o;
    const double t = x[1], du = o[O_DU], dn = o[O_DU_NEXT];
    const unsigned char lim = o[O_LIMITED] != 0.0;
    unsigned char cmd[CMD_SIZE];
    cmd[0] = self->cmd_magic;
    cmd[1] = self->version;
    put_u64(cmd + 2, (uint64_t)seq); put_f64(cmd + 10, t); put_f64(cmd + 18, du); put_f64(cmd + 26, dn);
    cmd[34] = lim;
    long long j = seq & self->hist_mask;
    ((int64_t *)self->hseq.buf)[j] = (int64_t)seq;
    ((double *)self->hu.buf)[j] = x[4];
    ((double *)self->hr.buf)[j] = du;
    int dropped = 0;
    if (self->has_ring) {
        unsigned char *base = self->ring.buf;
        if (!base[RING_FAILED]) {  /* the writer failed: nobody empties the ring (RingRecorder.offer) */
            int64_t *w = self->widx.buf;
            unsigned char *slot = base + RING_HDR + (*w % self->slots) * RING_SLOT;
            if (__atomic_load_n(slot, __ATOMIC_ACQUIRE)) {
                dropped = 1;
            } else {
                unsigned char *p = slot + 1;
                p[0] = self->group_id;
                put_f64(p + 1, t);
                p += 9;  /* meas: seq, t, i, v, u, i_load */
                put_u64(p, (uint64_t)seq);
                for (int m = 1; m < 6; m++) put_f64(p + 8 * m, x[m]);
                p += 48;  /* z_in: seq, t, P_r_in, P_r_in_dot, stepped */
                put_u64(p, (uint64_t)seq); put_f64(p + 8, t); put_f64(p + 16, x[6]); put_f64(p + 24, x[7]);
                p[32] = 1;
                p += 33;  /* cmd: seq, t, du/dt, du/dt next, limited */
                memcpy(p, cmd + 2, CMD_SIZE - 2);
                __atomic_store_n(slot, (unsigned char)1, __ATOMIC_RELEASE);  /* publish: the payload is complete */
                *w += 1;
            }
        }
    }
    PyObject *payload = PyBytes_FromStringAndSize((const char *)cmd, CMD_SIZE);
    if (payload == NULL)
        return NULL;
    double qdot;
    PyObject *P_out = port_rates(o, &qdot);
    if (P_out == NULL) {
        Py_DECREF(payload);
        return NULL;
    }
    return Py_BuildValue("NddOONdO", payload, du, dn, lim ? Py_True : Py_False, o[O_LATE] != 0.0 ? Py_True : Py_False,
                         P_out, qdot, dropped ? Py_True : Py_False);
}

/* accept(payload, last_seq, last_t) -> the measurement's values (seq, t, i, v, u, i_load), exactly as schemas.codec
 * MEAS.decode gives them, when the daemon's checks in _tick would take it as the next ordinary sample: well formed,
 * finite and admissible (seq < seq_limit, t in [t_min, t_limit)), v in [v_min, v_max], |i| and |i_load| <= i_max,
 * |u| <= u_max, seq after last_seq >= 0 (not the first sample or a restart) by at most max_gap, t after last_t and
 * within clock_tol of last_t + (seq - last_seq) * period (the plant's clock: docs/protocol.md); else None, and the
 * Python checks decide (and name the reason). */
static PyObject *TickWriter_accept(TickWriter *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs != 3) {
        PyErr_SetString(PyExc_TypeError, "accept(payload, last_seq, last_t) takes 3 arguments");
        return NULL;
    }
    if (!self->has_meas) {
        PyErr_SetString(PyExc_RuntimeError, "TickWriter: no measurement layout given");
        return NULL;
    }
    long long last_seq = PyLong_AsLongLong(args[1]);
    double last_t = PyFloat_AsDouble(args[2]);
    if (PyErr_Occurred())
        return NULL;
    if (!PyBytes_Check(args[0]) || PyBytes_GET_SIZE(args[0]) != MEAS_SIZE || last_seq < 0)
        Py_RETURN_NONE;
    const unsigned char *p = (const unsigned char *)PyBytes_AS_STRING(args[0]);
    if (p[0] != self->meas_magic || p[1] != self->version)
        Py_RETURN_NONE;
    uint64_t seq;
    double x[5];
    memcpy(&seq, p + 2, 8);
    memcpy(x, p + 10, sizeof(x));
    for (int j = 0; j < 5; j++)
        if (!isfinite(x[j]))
            Py_RETURN_NONE;
    if (!(self->v_min <= x[2] && x[2] <= self->v_max) || fabs(x[1]) > self->i_max || fabs(x[4]) > self->i_max
        || !(fabs(x[3]) <= self->u_max))
        Py_RETURN_NONE;
    if (seq >= self->seq_limit || !(self->t_min <= x[0] && x[0] < self->t_limit))
        Py_RETURN_NONE;
    if ((long long)seq <= last_seq || !(x[0] > last_t) || (long long)seq - last_seq > self->max_gap)
        Py_RETURN_NONE;
    if (!(fabs((x[0] - last_t) - (double)((long long)seq - last_seq) * self->period) <= self->clock_tol))
        Py_RETURN_NONE;
    return Py_BuildValue("(Kddddd)", (unsigned long long)seq, x[0], x[1], x[2], x[3], x[4]);
}

static PyObject *TickWriter_close(TickWriter *self, PyObject *Py_UNUSED(ignored))
{
    TickWriter_release(self);
    Py_RETURN_NONE;
}

static PyMethodDef TickWriter_methods[] = {
    {"step", (PyCFunction)(void (*)(void))TickWriter_step, METH_FASTCALL,
     "step(seq, t, i, v, u, i_load, P_r_in, P_r_in_dot) -> (command payload, du_dt, du_dt_next, limited, late, "
     "P_r_out_port or None, Qdot_r_out_port, dropped)"},
    {"accept", (PyCFunction)(void (*)(void))TickWriter_accept, METH_FASTCALL,
     "accept(payload, last_seq, last_t) -> (seq, t, i, v, u, i_load) of an ordinary next sample, else None"},
    {"close", (PyCFunction)TickWriter_close, METH_NOARGS, "release the buffers (before the recorder closes its ring)"},
    {NULL, NULL, 0, NULL},
};

PyTypeObject TickWriterType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "service._kernel.TickWriter",
    .tp_basicsize = sizeof(TickWriter),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "The daemon's stepped tick after its checks: kernel step, command payload, history, recorder slot.",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)TickWriter_init,
    .tp_dealloc = (destructor)TickWriter_dealloc,
    .tp_methods = TickWriter_methods,
};
