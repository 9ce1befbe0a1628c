#include "kernel.h"

/* The source current limit (rlc.py's module docstring): a stage's di/dt is 0 while |i| is at imax and the branch
 * voltage would push it further. */
#define HELD(ii, ki) (lim && (((ii) >= imax && (ki) > 0.0) || ((ii) <= -imax && (ki) < 0.0)))

/* plant_steps(R, L, C, v_min, u_min, u_max, clip, r, h, n_sub, Pa, dP, ma, dm, i, v, u, i_max) -> (i, v, u):
 * service/plant/rlc.py RLCPlant.advance's RK4 loop, operation for operation (the HIL plant and sim at 10 kHz spent
 * most of their time in it). i_max = inf: no current limit. */
PyObject *plant_steps(PyObject *Py_UNUSED(mod), PyObject *const *args, Py_ssize_t nargs)
{
    double x[18];
    if (!float_args(args, nargs, 18, x, "plant_steps(R, L, C, v_min, u_min, u_max, clip, r, h, n_sub, Pa, dP, ma, dm, "
                                        "i, v, u, i_max)"))
        return NULL;
    const double R = x[0], L = x[1], C = x[2], vmin = x[3], umin = x[4], umax = x[5], r = x[7], h = x[8];
    const int clip = x[6] != 0.0;
    const long n_sub = (long)x[9];
    const double Pa = x[10], dP = x[11], ma = x[12], dm = x[13];
    double i = x[14], v = x[15], u = x[16];
    const double imax = x[17];
    const int lim = imax != INFINITY;
    const double hh = 0.5 * h, vmin2 = vmin * vmin;
    for (long k = 0; k < n_sub; k++) {
        double P0 = Pa + (double)k * dP;
        double P1 = P0 + dP;
        double Pm = P0 + 0.5 * dP;
        double m0 = ma + (double)k * dm;
        double mm = m0 + 0.5 * dm;
        double m1 = m0 + dm;
        double um_, ub;
        if (clip) {
            um_ = PYMIN(PYMAX(u + r * hh, umin), umax);
            ub = PYMIN(PYMAX(u + r * h, umin), umax);
        } else {
            um_ = u + r * hh;
            ub = u + r * h;
        }
        double i2 = v >= vmin ? P0 / v : P0 * v / vmin2;
        double ki1 = (u + m0 - R * i - v) / L;
        if (HELD(i, ki1))
            ki1 = 0.0;
        double kv1 = (i - i2) / C;
        double ii = i + hh * ki1;
        if (lim)
            ii = PYMIN(PYMAX(ii, -imax), imax);
        double vv = v + hh * kv1;
        i2 = vv >= vmin ? Pm / vv : Pm * vv / vmin2;
        double ki2 = (um_ + mm - R * ii - vv) / L;
        if (HELD(ii, ki2))
            ki2 = 0.0;
        double kv2 = (ii - i2) / C;
        ii = i + hh * ki2;
        if (lim)
            ii = PYMIN(PYMAX(ii, -imax), imax);
        vv = v + hh * kv2;
        i2 = vv >= vmin ? Pm / vv : Pm * vv / vmin2;
        double ki3 = (um_ + mm - R * ii - vv) / L;
        if (HELD(ii, ki3))
            ki3 = 0.0;
        double kv3 = (ii - i2) / C;
        ii = i + h * ki3;
        if (lim)
            ii = PYMIN(PYMAX(ii, -imax), imax);
        vv = v + h * kv3;
        i2 = vv >= vmin ? P1 / vv : P1 * vv / vmin2;
        double ki4 = (ub + m1 - R * ii - vv) / L;
        if (HELD(ii, ki4))
            ki4 = 0.0;
        double kv4 = (ii - i2) / C;
        i += h / 6.0 * (ki1 + 2.0 * ki2 + 2.0 * ki3 + ki4);
        if (lim)
            i = PYMIN(PYMAX(i, -imax), imax);
        v += h / 6.0 * (kv1 + 2.0 * kv2 + 2.0 * kv3 + kv4);
        u = ub;
    }
    return Py_BuildValue("(ddd)", i, v, u);
}
