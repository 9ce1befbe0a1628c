/* service._stopsignal: a stop signal (SIGINT, SIGTERM) arms SIGALRM in C, before Python's own handler is asked to
 * run, so that a process whose interpreter can no longer run Python code (a thread holding the GIL waits on a lock
 * that a thread waiting for the GIL holds) still ends: SIGALRM's default action terminates it grace_s seconds after
 * the first stop signal. Python's handler (the clean stop) is still called, as the kernel would have called it.
 *
 * arm(signum, grace_s) wraps the handler installed for signum now (install the Python one first). Everything the
 * wrapper does is async-signal-safe (sigaction, alarm, and Python's own C-level handler). */
#define _POSIX_C_SOURCE 200809L
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <signal.h>
#include <string.h>
#include <unistd.h>

#define NSIG_MAX 65

static struct sigaction previous[NSIG_MAX];
static volatile sig_atomic_t grace[NSIG_MAX];
static volatile sig_atomic_t alarm_armed = 0;

static void on_stop(int sig, siginfo_t *info, void *ctx) {
    if (!alarm_armed) { /* the first stop signal sets the deadline; later ones do not move it */
        struct sigaction cur;
        /* SIGALRM must end the process: an ignored one gets its default action back; a C-level handler installed
         * for it (faulthandler.register(SIGALRM, chain=True): the stacks, then the default action) stays */
        if (sigaction(SIGALRM, NULL, &cur) == 0 && !(cur.sa_flags & SA_SIGINFO) && cur.sa_handler == SIG_IGN) {
            struct sigaction dfl;
            memset(&dfl, 0, sizeof dfl);
            dfl.sa_handler = SIG_DFL;
            sigemptyset(&dfl.sa_mask);
            sigaction(SIGALRM, &dfl, NULL);
        }
        alarm((unsigned)grace[sig]);
        alarm_armed = 1;
    }
    const struct sigaction *p = &previous[sig];
    if (p->sa_flags & SA_SIGINFO) {
        if (p->sa_sigaction != NULL) p->sa_sigaction(sig, info, ctx);
    } else if (p->sa_handler == SIG_DFL) { /* nobody else handles it: its default action, now */
        sigaction(sig, p, NULL);
        raise(sig);
    } else if (p->sa_handler != SIG_IGN) {
        p->sa_handler(sig);
    }
}

static PyObject *arm(PyObject *self, PyObject *args) {
    (void)self;
    int sig, grace_s;
    if (!PyArg_ParseTuple(args, "ii", &sig, &grace_s)) return NULL;
    if (sig <= 0 || sig >= NSIG_MAX || sig == SIGALRM || grace_s < 1) {
        PyErr_Format(PyExc_ValueError, "arm(%d, %d): a signal other than SIGALRM, and grace_s >= 1", sig, grace_s);
        return NULL;
    }
    struct sigaction now, ours;
    if (sigaction(sig, NULL, &now) != 0) return PyErr_SetFromErrno(PyExc_OSError);
    if (now.sa_sigaction == on_stop && (now.sa_flags & SA_SIGINFO)) { /* armed already: new grace only */
        grace[sig] = grace_s;
        Py_RETURN_NONE;
    }
    previous[sig] = now;
    grace[sig] = grace_s;
    memset(&ours, 0, sizeof ours);
    ours.sa_sigaction = on_stop;
    ours.sa_flags = SA_SIGINFO | SA_ONSTACK | (now.sa_flags & SA_RESTART);
    sigemptyset(&ours.sa_mask);
    if (sigaction(sig, &ours, NULL) != 0) return PyErr_SetFromErrno(PyExc_OSError);
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"arm", arm, METH_VARARGS,
     "arm(signum, grace_s): the first time signum arrives, SIGALRM (default action: terminate) is set to fire in "
     "grace_s seconds, in C; then the handler installed before arm() runs as usual."},
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_stopsignal", NULL, -1, methods, NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__stopsignal(void) { return PyModule_Create(&module); }
