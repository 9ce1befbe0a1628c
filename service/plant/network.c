#include "kernel.h"

/* network_steps(h, n_sub, src, r, lines, node_C, loads, i_s, u_s, i_l, v_n): service/plant/network.py steps(),
 * operation for operation (the same results to the bit; tests/plant/test_network.py). The arrays are writable
 * buffers of doubles (array('d')); i_s, u_s, i_l and v_n are updated in place. */

enum { SRC_W = 5, LINE_W = 5, LOAD_W = 5, MAX_ELEMS = 4096 };

typedef struct {
    const double *src, *r, *lines, *node_C, *loads;
    Py_ssize_t ns, nl, nn, nld;
    double *inj;
} Net;

static void derivatives(const Net *w, double kf, const double *u, const double *xs, const double *xl,
                        const double *xv, double *ds, double *dl, double *dv)
{
    double *inj = w->inj;
    for (Py_ssize_t n = 0; n < w->nn; n++)
        inj[n] = 0.0;
    for (Py_ssize_t j = 0; j < w->ns; j++) {
        const double *o = w->src + SRC_W * j;
        double d = (u[j] - o[0] * xs[j] - xv[j]) / o[1];
        const double im = o[4];
        if (im != INFINITY && ((xs[j] >= im && d > 0.0) || (xs[j] <= -im && d < 0.0)))
            d = 0.0; /* at its current limit, pushed further */
        ds[j] = d;
        inj[j] += xs[j];
    }
    for (Py_ssize_t j = 0; j < w->nl; j++) {
        const double *o = w->lines + LINE_W * j;
        if (o[4] != 0.0) {
            Py_ssize_t a = (Py_ssize_t)o[2], b = (Py_ssize_t)o[3];
            dl[j] = (xv[a] - xv[b] - o[0] * xl[j]) / o[1];
            inj[a] -= xl[j];
            inj[b] += xl[j];
        } else {
            dl[j] = 0.0;
        }
    }
    for (Py_ssize_t j = 0; j < w->nld; j++) {
        const double *o = w->loads + LOAD_W * j;
        Py_ssize_t n = (Py_ssize_t)o[0];
        double v = xv[n];
        if (o[1] == 0.0) {
            double P = o[2] + kf * o[3];
            double vmin = o[4];
            inj[n] -= v >= vmin ? P / v : P * v / (vmin * vmin);
        } else {
            inj[n] -= v * o[2];
        }
    }
    for (Py_ssize_t n = 0; n < w->nn; n++)
        dv[n] = inj[n] / w->node_C[n];
}

static int get_buffer(PyObject *obj, Py_buffer *view, int writable, Py_ssize_t *count, const char *name)
{
    if (PyObject_GetBuffer(obj, view, PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0)) < 0)
        return 0;
    if (view->itemsize != sizeof(double) || view->format == NULL || strcmp(view->format, "d") != 0) {
        PyErr_Format(PyExc_TypeError, "network_steps: %s must be a buffer of doubles (array('d'))", name);
        PyBuffer_Release(view);
        return 0;
    }
    *count = view->len / (Py_ssize_t)sizeof(double);
    return 1;
}

PyObject *network_steps(PyObject *Py_UNUSED(mod), PyObject *const *args, Py_ssize_t nargs)
{
    static const char *names[] = {"src", "r", "lines", "node_C", "loads", "i_s", "u_s", "i_l", "v_n"};
    if (nargs != 11) {
        PyErr_SetString(PyExc_TypeError,
                        "network_steps(h, n_sub, src, r, lines, node_C, loads, i_s, u_s, i_l, v_n) takes 11 arguments");
        return NULL;
    }
    double h = PyFloat_AsDouble(args[0]);
    long n_sub = PyLong_AsLong(args[1]);
    if (PyErr_Occurred())
        return NULL;
    Py_buffer views[9];
    Py_ssize_t counts[9];
    int got = 0;
    PyObject *result = NULL;
    double *scratch = NULL;
    for (; got < 9; got++)
        if (!get_buffer(args[2 + got], &views[got], got >= 5, &counts[got], names[got]))
            goto done;
    Net w = {.src = views[0].buf, .r = views[1].buf, .lines = views[2].buf, .node_C = views[3].buf,
             .loads = views[4].buf, .ns = counts[5], .nl = counts[7], .nn = counts[8], .nld = counts[4] / LOAD_W};
    if (counts[0] != SRC_W * w.ns || counts[1] != w.ns || counts[2] != LINE_W * w.nl || counts[3] != w.nn ||
        counts[4] != LOAD_W * w.nld || counts[6] != w.ns || w.ns > w.nn || w.nn > MAX_ELEMS || w.nl > MAX_ELEMS) {
        PyErr_SetString(PyExc_ValueError, "network_steps: array lengths do not fit each other");
        goto done;
    }
    for (Py_ssize_t j = 0; j < w.nl; j++) {
        const double *o = w.lines + LINE_W * j;
        if (!(o[2] >= 0 && o[2] < (double)w.nn && o[3] >= 0 && o[3] < (double)w.nn)) {
            PyErr_SetString(PyExc_ValueError, "network_steps: a line's node index is out of range");
            goto done;
        }
    }
    for (Py_ssize_t j = 0; j < w.nld; j++) {
        double n = w.loads[LOAD_W * j];
        if (!(n >= 0 && n < (double)w.nn)) {
            PyErr_SetString(PyExc_ValueError, "network_steps: a load's node index is out of range");
            goto done;
        }
    }
    Py_ssize_t ns = w.ns, nl = w.nl, nn = w.nn;
    scratch = PyMem_Calloc((size_t)(5 * ns + 5 * nl + 6 * nn + 1), sizeof(double));
    if (scratch == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    double *k1s = scratch, *k2s = k1s + ns, *k3s = k2s + ns, *k4s = k3s + ns, *ts = k4s + ns;
    double *k1l = ts + ns, *k2l = k1l + nl, *k3l = k2l + nl, *k4l = k3l + nl, *tl = k4l + nl;
    double *k1v = tl + nl, *k2v = k1v + nn, *k3v = k2v + nn, *k4v = k3v + nn, *tv = k4v + nn;
    w.inj = tv + nn;
    double *uu = PyMem_Calloc((size_t)ns + 1, sizeof(double));
    if (uu == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    double *i_s = views[5].buf, *u_s = views[6].buf, *i_l = views[7].buf, *v_n = views[8].buf;
    const double hh = 0.5 * h;
    for (long k = 0; k < n_sub; k++) {
        double fk = (double)k;
        for (int stage = 0; stage < 4; stage++) {
            double frac, tau;
            const double *xs, *xl, *xv;
            double *ds, *dl, *dv;
            if (stage == 0) {
                frac = 0.0; tau = 0.0; xs = i_s; xl = i_l; xv = v_n; ds = k1s; dl = k1l; dv = k1v;
            } else if (stage == 1) {
                frac = 0.5; tau = hh; xs = ts; xl = tl; xv = tv; ds = k2s; dl = k2l; dv = k2v;
            } else if (stage == 2) {
                frac = 0.5; tau = hh; xs = ts; xl = tl; xv = tv; ds = k3s; dl = k3l; dv = k3v;
            } else {
                frac = 1.0; tau = h; xs = ts; xl = tl; xv = tv; ds = k4s; dl = k4l; dv = k4v;
            }
            for (Py_ssize_t j = 0; j < ns; j++)
                uu[j] = PYMIN(PYMAX(u_s[j] + w.r[j] * tau, w.src[SRC_W * j + 2]), w.src[SRC_W * j + 3]);
            derivatives(&w, fk + frac, uu, xs, xl, xv, ds, dl, dv);
            if (stage < 3) {
                double step = stage == 2 ? h : hh;
                const double *dns = stage == 2 ? k3s : (stage == 0 ? k1s : k2s);
                const double *dnl = stage == 2 ? k3l : (stage == 0 ? k1l : k2l);
                const double *dnv = stage == 2 ? k3v : (stage == 0 ? k1v : k2v);
                for (Py_ssize_t j = 0; j < ns; j++) {
                    ts[j] = i_s[j] + step * dns[j];
                    const double im = w.src[SRC_W * j + 4];
                    if (im != INFINITY)
                        ts[j] = PYMIN(PYMAX(ts[j], -im), im);
                }
                for (Py_ssize_t j = 0; j < nl; j++)
                    tl[j] = i_l[j] + step * dnl[j];
                for (Py_ssize_t j = 0; j < nn; j++)
                    tv[j] = v_n[j] + step * dnv[j];
            }
        }
        const double h6 = h / 6.0;
        for (Py_ssize_t j = 0; j < ns; j++) {
            i_s[j] += h6 * (k1s[j] + 2.0 * k2s[j] + 2.0 * k3s[j] + k4s[j]);
            const double im = w.src[SRC_W * j + 4];
            if (im != INFINITY)
                i_s[j] = PYMIN(PYMAX(i_s[j], -im), im);
            u_s[j] = PYMIN(PYMAX(u_s[j] + w.r[j] * h, w.src[SRC_W * j + 2]), w.src[SRC_W * j + 3]);
        }
        for (Py_ssize_t j = 0; j < nl; j++)
            if (w.lines[LINE_W * j + 4] != 0.0)
                i_l[j] += h6 * (k1l[j] + 2.0 * k2l[j] + 2.0 * k3l[j] + k4l[j]);
        for (Py_ssize_t j = 0; j < nn; j++)
            v_n[j] += h6 * (k1v[j] + 2.0 * k2v[j] + 2.0 * k3v[j] + k4v[j]);
    }
    PyMem_Free(uu);
    result = Py_None;
    Py_INCREF(result);
done:
    PyMem_Free(scratch);
    for (int j = 0; j < got; j++)
        PyBuffer_Release(&views[j]);
    return result;
}
