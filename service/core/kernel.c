/* Compiled twin of service/core/control.py's ControlCore.step (and the estimator it calls).
 *
 * Same operations in the same order as the Python reference, IEEE double, no fused multiply-add
 * (built with -ffp-contract=off), libm's exp and sqrt (the ones Python's math module calls): the
 * results are bit-identical to the Python core, which tests/core/test_kernel.py checks for every
 * controller kind, both mappings and delays 0..3. The Python module stays the specification; this
 * file is only its fast path. No clocks, no I/O, no globals: all state lives in the Kernel object.
 *
 * Python's min(a, b) returns a unless b < a, max(a, b) returns a unless b > a (NaN handling
 * included); PYMIN / PYMAX copy that. Where Python would raise ZeroDivisionError (a zero voltage
 * inside the prediction), C gives inf or NaN, which the step's finiteness check turns into
 * du/dt = 0: the safe answer.
 */
#include "kernel.h"

static void predict(double *pi, double *pv, double *pu, double P, double r, double T, int n, double R, double L,
                    double C)
{
    double i = *pi, v = *pv, u = *pu;
    double h = T / n, hh = 0.5 * h;
    for (int k = 0; k < n; k++) {
        double k1i = (u - R * i - v) / L;
        double k1v = (i - P / v) / C;
        double ii = i + hh * k1i, vv = v + hh * k1v;
        double um = u + hh * r;
        double k2i = (um - R * ii - vv) / L;
        double k2v = (ii - P / vv) / C;
        ii = i + hh * k2i;
        vv = v + hh * k2v;
        double k3i = (um - R * ii - vv) / L;
        double k3v = (ii - P / vv) / C;
        ii = i + h * k3i;
        vv = v + h * k3v;
        double u1 = u + h * r;
        double k4i = (u1 - R * ii - vv) / L;
        double k4v = (ii - P / vv) / C;
        i = i + h / 6.0 * (k1i + 2.0 * k2i + 2.0 * k3i + k4i);
        v = v + h / 6.0 * (k1v + 2.0 * k2v + 2.0 * k3v + k4v);
        u = u1;
    }
    *pi = i; *pv = v; *pu = u;
}

/* core.predict_in_range: predict, then u held in [u_min, u_max] */
static void predict_in_range(double *pi, double *pv, double *pu, double P, double r, double T, int n, double R,
                             double L, double C, double u_min, double u_max)
{
    predict(pi, pv, pu, P, r, T, n, R, L, C);
    if (*pu > u_max)
        *pu = u_max;
    else if (*pu < u_min)
        *pu = u_min;
}

static void predict_with_sensitivity(double i, double v, double u, double P, double r, double T, int n, double R,
                                     double L, double C, double *pi, double *pv, double *pu, double *psi,
                                     double *psv)
{
    double h = T / n, hh = 0.5 * h;
    double si = 0.0, sv = 0.0, tau = 0.0;
    for (int k = 0; k < n; k++) {
        double k1i = (u - R * i - v) / L;
        double k1v = (i - P / v) / C;
        double g = P / (v * v);
        double k1si = (tau - R * si - sv) / L;
        double k1sv = (si + g * sv) / C;
        double ii = i + hh * k1i, vv = v + hh * k1v;
        double s2i = si + hh * k1si, s2v = sv + hh * k1sv;
        double um = u + hh * r;
        g = P / (vv * vv);
        double k2i = (um - R * ii - vv) / L;
        double k2v = (ii - P / vv) / C;
        double k2si = (tau + hh - R * s2i - s2v) / L;
        double k2sv = (s2i + g * s2v) / C;
        ii = i + hh * k2i;
        vv = v + hh * k2v;
        double s3i = si + hh * k2si, s3v = sv + hh * k2sv;
        g = P / (vv * vv);
        double k3i = (um - R * ii - vv) / L;
        double k3v = (ii - P / vv) / C;
        double k3si = (tau + hh - R * s3i - s3v) / L;
        double k3sv = (s3i + g * s3v) / C;
        ii = i + h * k3i;
        vv = v + h * k3v;
        double s4i = si + h * k3si, s4v = sv + h * k3sv;
        double u1 = u + h * r;
        g = P / (vv * vv);
        double k4i = (u1 - R * ii - vv) / L;
        double k4v = (ii - P / vv) / C;
        double k4si = (tau + h - R * s4i - s4v) / L;
        double k4sv = (s4i + g * s4v) / C;
        i = i + h / 6.0 * (k1i + 2.0 * k2i + 2.0 * k3i + k4i);
        v = v + h / 6.0 * (k1v + 2.0 * k2v + 2.0 * k3v + k4v);
        si = si + h / 6.0 * (k1si + 2.0 * k2si + 2.0 * k3si + k4si);
        sv = sv + h / 6.0 * (k1sv + 2.0 * k2sv + 2.0 * k3sv + k4sv);
        u = u1;
        tau = tau + h;
    }
    *pi = i; *pv = v; *pu = u; *psi = si; *psv = sv;
}

static double solve_rate_for_target(double R, double T, double i1, double u1, double si, double y_target)
{
    double a = R * si * si - T * si;
    double b = 2.0 * R * i1 * si - u1 * si - T * i1;
    double c = R * i1 * i1 - u1 * i1 - y_target;
    if (fabs(a) * fabs(c) < 1e-12 * b * b)
        return b != 0.0 ? -c / b : 0.0;
    double disc = b * b - 4.0 * a * c;
    if (disc < 0.0)
        return -b / (2.0 * a);
    double q = -0.5 * (b + copysign(sqrt(disc), b));
    return q != 0.0 ? c / q : 0.0;
}

static double y_reference(double P_in, double v, double v_ref, double keC)
{
    if (keC == 0.0)
        return P_in * v_ref / v;
    return P_in + keC * (v * v - v_ref * v_ref);
}

/* control.linearisation_rate: the previous command, clipped to what the slew limit and u's range allow */
static double linearisation_rate(double r_prev, double u_p, double T, double u_min, double u_max, double r_max)
{
    double r_lo = PYMAX(-r_max, (u_min - u_p) / T);
    double r_hi = PYMAX(r_lo, PYMIN(r_max, (u_max - u_p) / T));
    return PYMIN(PYMAX(r_prev, r_lo), r_hi);
}

/* control.nested_output: sigma (W/s) and its gradient g[0..2] = d sigma / d(i, v, u); returns 1 at the current
   limit */
static int nested_output(double i, double v, double u, double P, double P_ff, double Pdot, double R, double L,
                         double C, double v_ref, double K_P, double K_E, double i_max, double *sigma, double *g)
{
    double dv = (i - P / v) / C;
    double di = (u - R * i - v) / L;
    double Pb = v * i;
    double dPb = dv * i + v * di;
    double P_ref = P_ff - K_E * (0.5 * C * (v * v - v_ref * v_ref));
    double dP_ref = Pdot - K_E * (Pb - P);
    double gr_i = 0.0, gr_v = -K_E * C * v;
    double gd_i = -K_E * v, gd_v = -K_E * i;
    int limited = 0;
    if (i_max > 0.0) {
        double P_max = v * i_max;
        if (P_ref > P_max || P_ref < -P_max) {
            double im = P_ref > 0.0 ? i_max : -i_max;
            P_ref = v * im;
            dP_ref = dv * im;
            gr_i = 0.0;
            gr_v = im;
            gd_i = im / C;
            gd_v = im * P / (v * v * C);
            limited = 1;
        }
    }
    *sigma = dPb - dP_ref + K_P * (Pb - P_ref);
    g[0] = i / C + dv - v * R / L - gd_i + K_P * (v - gr_i);
    g[1] = i * P / (v * v * C) + di - v / L - gd_v + K_P * (i - gr_v);
    g[2] = v / L;
    return limited;
}

/* ControlCore._pi_step: the cascaded PI baseline on the raw sample */
static void pi_step(Kernel *k, double si_, double sv, double si2)
{
    double xv = k->pi_xv, xi = k->pi_xi;
    double ev = k->v_ref - sv;
    double i_ref = si2 + k->kp_v * ev + k->ki_v * xv;
    double i_sat = i_ref;
    if (k->i_max > 0.0)
        i_sat = PYMIN(PYMAX(i_ref, -k->i_max), k->i_max);
    double ei = i_sat - si_;
    double u_des = sv + k->R * si_ + k->kp_i * ei + k->ki_i * xi;
    double u_sat = PYMIN(PYMAX(u_des, k->u_min), k->u_max);
    if (u_sat == u_des) {
        xi = xi + ei * k->T;
        if (i_sat == i_ref)
            xv = xv + ev * k->T;
    }
    k->pi_xv = xv;
    k->pi_xi = xi;
    k->pi_u = u_sat;
}

static void kernel_reset(Kernel *k)
{
    k->pi_xv = k->pi_xi = k->pi_u = 0.0;
    k->has_t = 0;
    k->t_last = k->S0 = k->S1 = k->S2 = 0.0;
    for (int c = 0; c < 3; c++) {
        k->Sy[c] = k->Say[c] = k->ref[c] = 0.0;
        k->o[O_FITV + c] = k->o[O_FITS + c] = 0.0;
    }
    k->o[O_COUNT] = 0.0;
    k->o[O_ZRUN0] = k->o[O_ZRUN1] = 0.0;
    k->has_last = 0;
    for (int j = 0; j <= k->d; j++) {
        k->pending_seq[j] = SEQ_NONE;
        k->pending[2 * j] = k->pending[2 * j + 1] = 0.0;
    }
    k->r_prev = 0.0;
    k->late = 0;
    k->last_seq_u = -2;
    k->last_u = 0.0;
    k->x_seq = -2;
    k->x_hat[0] = k->x_hat[1] = k->x_hat[2] = 0.0;
    k->x_P = 0.0;
    k->o[O_STEPS] = 0.0;
}

/* EwLineFit.update3 (and its first-sample path in update); returns 0 if t did not advance. */
static int fit_update(Kernel *k, double t, const double y[3])
{
    double *val = k->o + O_FITV, *slo = k->o + O_FITS;
    if (!k->has_t) {
        k->has_t = 1;
        k->t_last = t;
        k->S0 = 1.0;
        for (int c = 0; c < 3; c++) {
            k->ref[c] = y[c];
            k->Sy[c] = k->Say[c] = 0.0;
            val[c] = y[c];
            slo[c] = 0.0;
        }
        k->o[O_COUNT] = 1.0;
        return 1;
    }
    double dt = t - k->t_last;
    if (!(dt > 0.0))
        return 0;
    k->t_last = t;
    double w = exp(-dt / k->tau);
    double S0 = k->S0, S1 = k->S1;
    double S2 = (k->S2 + 2.0 * dt * S1 + dt * dt * S0) * w;
    S1 = (S1 + dt * S0) * w;
    S0 = S0 * w + 1.0;
    k->S0 = S0; k->S1 = S1; k->S2 = S2;
    double det = S0 * S2 - S1 * S1;
    double sy[3], sa[3];
    for (int c = 0; c < 3; c++) {
        sy[c] = k->Sy[c] * w + (y[c] - k->ref[c]);
        sa[c] = (k->Say[c] + dt * k->Sy[c]) * w;
    }
    for (int c = 0; c < 3; c++) {
        k->Sy[c] = sy[c];
        k->Say[c] = sa[c];
    }
    if (det > 1e-12 * S0 * S0 * (k->tau * k->tau)) {
        for (int c = 0; c < 3; c++) {
            double b = (S0 * sa[c] - S1 * sy[c]) / det;
            val[c] = k->ref[c] + (sy[c] - b * S1) / S0;
            slo[c] = -b;
        }
    } else {
        for (int c = 0; c < 3; c++) {
            val[c] = y[c];
            slo[c] = 0.0;
        }
    }
    k->o[O_COUNT] += 1.0;
    return 1;
}

/* RLCEnergy.update with u_m = 0 (service/core/energy.py). */
static void energy_update(double *e, double R, double L, double C, double i, double v, double u, double i2,
                          double di, double dv, double du, double di2)
{
    const double u_m = 0.0;
    double E = 0.5 * (L * i * i + C * v * v);
    double E_t = 0.5 * (L * di * di + C * dv * dv);
    double D = R * i * i;
    double p = L * i * di + C * v * dv;
    double ddi = (du - R * di - dv) / L;
    double ddv = (di - di2) / C;
    double pdot = L * di * di + C * dv * dv + L * i * ddi + C * v * ddv;
    double P_u = u * i, Qdot_u = u * di - i * du, P_m = u_m * i, Qdot_m = u_m * di;
    e[E_E] = E; e[E_ET] = E_t; e[E_D] = D; e[E_P] = p; e[E_PDOT] = pdot;
    e[E_TAU] = D > 0.0 ? E / D : INFINITY;
    e[E_PU] = P_u; e[E_QDU] = Qdot_u; e[E_PM] = P_m;
    e[E_PL] = v * i2;
    e[E_QDL] = v * di2 - i2 * dv;
    e[E_YZ] = D - P_u - P_m;
    e[E_YZB] = -(e[E_PL] + p);
    e[E_ETA] = 4.0 * E_t + 2.0 * (R * i - u - u_m) * di;
    e[E_PRO] = p + D - P_u - P_m;
    e[E_QRO] = -pdot + 4.0 * E_t - Qdot_u - Qdot_m;
    e[E_PROP] = -e[E_PL];
    e[E_QROP] = e[E_QDL] + 2.0 * (i * dv - v * di);
}

/* slot of sample seq in pending: seq mod (d + 1), non-negative as Python's % */
static int slot_of(const Kernel *k, long long seq)
{
    long long m = (long long)k->d + 1;
    long long j = seq % m;
    return (int)(j < 0 ? j + m : j);
}

/* ControlCore.issued */
static double issued(const Kernel *k, long long seq)
{
    int j = slot_of(k, seq);
    if (k->pending_seq[j] == seq)
        return k->pending[2 * j];
    j = slot_of(k, seq - 1);
    return k->pending_seq[j] == seq - 1 ? k->pending[2 * j + 1] : 0.0;
}

static void remember(Kernel *k, long long seq, double r, double plan)
{
    int j = slot_of(k, seq);
    k->pending_seq[j] = seq;
    k->pending[2 * j] = r;
    k->pending[2 * j + 1] = plan;
}

long long kernel_seq(const Kernel *k)
{
    long long seq;
    memcpy(&seq, k->o + O_SEQ, sizeof seq);
    return seq;
}

/* ControlCore._law: du/dt within the limits for the period from t_{k+dd}, from the state predicted there; *raw
   before the limits, *u_zp the u_z it implies. */
static double law(Kernel *k, double i_p, double v_p, double u_p, double P_load, double P_in, double P_in_dot,
                  int dd, double r_prev, double *raw_p, double *u_zp)
{
    const double R = k->R, L = k->L, C = k->C, T = k->T;
    const double u_min = k->u_min, u_max = k->u_max, r_max = k->r_max, i_floor = k->i_floor;
    const double v_ref = k->v_ref, K = k->K, alpha = k->alpha, phi = k->phi, decay = k->decay, keC = k->keC;
    double P_app = P_load + (-P_in_dot) * ((double)dd + 0.5) * T;
    double P_in_app = P_in + P_in_dot * (double)dd * T;
    double u_z = 0.0, r;

    if (k->kind == K_FIXED) {
        r = 0.0;
    } else if (k->kind == K_LQR) {
        double P_l = -P_in;
        double i_ref = P_l / v_ref;
        double u_ref = v_ref + R * P_l / v_ref;
        double u_des = u_ref - k->lK1 * (i_p - i_ref) - k->lK2 * (v_p - v_ref);
        r = (u_des - u_p) / T;
    } else if (k->kind == K_PI) {
        r = (k->pi_u - u_p) / T;
    } else if (k->kind == K_NESTED) {
        double r0 = linearisation_rate(r_prev, u_p, T, u_min, u_max, r_max);
        double Pd = -P_in_dot;
        double P0 = P_load + Pd * (double)dd * T;
        double F0 = (k->load_ref ? -P_in : P_load) + Pd * (double)dd * T;
        double i1, v1, u1, si, sv, sig0, sig1, g0[3], g[3];
        predict_with_sensitivity(i_p, v_p, u_p, P_app, r0, T, k->n_pred, R, L, C, &i1, &v1, &u1, &si, &sv);
        nested_output(i_p, v_p, u_p, P0, F0, Pd, R, L, C, v_ref, k->nK_P, k->nK_E, k->i_max, &sig0, g0);
        k->ilim = nested_output(i1, v1, u1, P0 + Pd * T, F0 + Pd * T, Pd, R, L, C, v_ref, k->nK_P, k->nK_E,
                                k->i_max, &sig1, g);
        r = r0 + (sig0 * k->n_decay - sig1) / (g[0] * si + g[1] * sv + g[2] * T);
        u_z = u_p * (u_p - R * i_p - v_p) / L - i_p * r;
    } else if (k->kind == K_BM) {
        double dv = (i_p - P_app / v_p) / C;
        double u_des = R * i_p + v_ref - L * (k->bPi / (v_p * v_p) + k->bK3) * dv - k->bK1 * (v_p - v_ref)
                       - k->bK2 * dv;
        r = (u_des - u_p) / T;
    } else {
        double y_p = R * i_p * i_p - u_p * i_p;
        double e_p = y_p - y_reference(P_in_app, v_p, v_ref, keC);
        double di = (u_p - R * i_p - v_p) / L;
        if (k->continuous) {
            double dv = (i_p - P_app / v_p) / C;
            double dy_ref;
            if (keC == 0.0)
                dy_ref = P_in_dot * v_ref / v_p - P_in_app * v_ref * dv / (v_p * v_p);
            else
                dy_ref = P_in_dot + 2.0 * keC * v_p * dv;
            if (k->kind == K_FBLC) {
                u_z = -K * e_p + dy_ref - 2.0 * (R * i_p - u_p) * di;
                if (!k->cancel_Et)
                    u_z = u_z - 2.0 * (L * di * di + C * dv * dv);
            } else {
                double sat;
                if (phi > 0.0)
                    sat = PYMAX(-1.0, PYMIN(1.0, e_p / phi));
                else
                    sat = e_p > 0 ? 1.0 : (e_p < 0 ? -1.0 : 0.0);
                u_z = -alpha * sat + dy_ref;
            }
            double i_f = i_p >= 0.0 ? PYMAX(i_p, i_floor) : PYMIN(i_p, -i_floor);
            r = (u_p * di - u_z) / i_f;
        } else {
            double r0 = linearisation_rate(r_prev, u_p, T, u_min, u_max, r_max);
            double i1, v1, u1, sens, sens_v;
            predict_with_sensitivity(i_p, v_p, u_p, P_app, r0, T, k->n_pred, R, L, C, &i1, &v1, &u1, &sens,
                                     &sens_v);
            double e1;
            if (k->kind == K_FBLC) {
                e1 = e_p * decay;
                if (!k->cancel_Et) {
                    double dv = (i_p - P_app / v_p) / C;
                    e1 = e1 - 2.0 * (L * di * di + C * dv * dv) * T;
                }
            } else {
                double sat = phi > 0.0 ? PYMAX(-1.0, PYMIN(1.0, e_p / phi)) : copysign(1.0, e_p);
                double stepv = alpha * T * sat;
                e1 = fabs(stepv) >= fabs(e_p) ? 0.0 : e_p - stepv;
            }
            double y_target = y_reference(P_in + P_in_dot * (double)(dd + 1) * T, v1, v_ref, keC) + e1;
            r = r0 + solve_rate_for_target(R, T, i1, u1, sens, y_target);
            u_z = u_p * di - i_p * r;
        }
    }

    double raw = r;
    if (!isfinite(r))
        r = 0.0;
    r = PYMIN(PYMAX(r, (u_min - u_p) / T), (u_max - u_p) / T);
    r = PYMIN(PYMAX(r, -r_max), r_max);
    *raw_p = raw;
    *u_zp = u_z;
    return r;
}

/* ControlCore._observe: the state the delay prediction starts from, x = x^- + g (y - x^-), x^- the previous
   estimate carried over one period at the rate the plant applied; from the sample after a gap. Before this step's
   command is remembered. */
static void observe(Kernel *k, long long seq, double si_, double sv, double su, double P_load, int late, double *pi,
                    double *pv, double *pu)
{
    double i, v, u;
    if (k->x_seq != seq - 1) {
        i = si_; v = sv; u = su;
    } else {
        double r = late ? 0.0 : issued(k, seq - 1 - k->d);
        i = k->x_hat[0]; v = k->x_hat[1]; u = k->x_hat[2];
        predict_in_range(&i, &v, &u, k->x_P, r, k->T, k->n_pred, k->R, k->L, k->C, k->u_min, k->u_max);
        const double g = k->obs;
        i = i + g * (si_ - i);
        v = v + g * (sv - v);
        u = u + g * (su - u);
    }
    k->x_seq = seq;
    k->x_hat[0] = i; k->x_hat[1] = v; k->x_hat[2] = u;
    k->x_P = P_load;
    *pi = i; *pv = v; *pu = u;
}

/* ControlCore.step; returns 1 if the estimator took the sample. */
int kernel_step(Kernel *k, long long seq, double t, double si_, double sv, double su, double si2, double P_in,
                double P_in_dot)
{
    const double R = k->R, L = k->L, C = k->C, T = k->T;
    const double u_min = k->u_min, u_max = k->u_max;
    const int d = k->d;
    double *o = k->o;
    if (d > 0 && k->late_tol > 0.0 && k->last_seq_u == seq - 1)
        k->late = fabs((su - k->last_u) - T * issued(k, seq - 1 - d)) > k->late_tol;
    k->last_seq_u = seq;
    k->last_u = su;
    const int late = k->late;
    double applied = d == 0 ? k->r_prev : late ? 0.0 : issued(k, seq - d);

    /* estimator */
    double y[3] = {si_, sv, si2};
    int took = fit_update(k, t, y);
    if (took) {
        double *fv = o + O_FITV, *fs = o + O_FITS, *e = o + O_EST;
        energy_update(e, R, L, C, fv[0], fv[1], su, fv[2], fs[0], fs[1], applied, fs[2]);
        if (k->has_last) {
            double h = t - k->last_t;
            o[O_ZRUN0] += 0.5 * h * (k->last_P + e[E_PROP]);
            o[O_ZRUN1] += 0.5 * h * (k->last_Q + e[E_QROP]);
        }
        k->has_last = 1;
        k->last_t = t;
        k->last_P = e[E_PROP];
        k->last_Q = e[E_QROP];
        o[O_HAS_EST] = 1.0;
        o[O_Z0] = o[O_ZRUN0];
        o[O_Z1] = o[O_ZRUN1];
    }

    /* state at the start of the period this command will act on */
    /* ControlCore.step: controller.load_power (nested: always measured; the reference is its feed-forward) */
    double P_load = k->load_ref && k->kind != K_NESTED ? -P_in : sv * si2;
    double Pdot = -P_in_dot;
    double i_p = si_, v_p = sv, u_p = su;
    if (k->obs > 0.0)
        observe(k, seq, si_, sv, su, P_load, late, &i_p, &v_p, &u_p);
    for (int j = 0; j < d; j++) {
        double r_j = late ? 0.0 : issued(k, seq - d + j);
        predict_in_range(&i_p, &v_p, &u_p, P_load + Pdot * ((double)j + 0.5) * T, r_j, T, k->n_pred, R, L, C,
                         u_min, u_max);
    }
    o[O_IPRED] = i_p; o[O_VPRED] = v_p; o[O_UPRED] = u_p;

    double y_z = R * si_ * si_ - su * si_;
    double y_ref = y_reference(P_in, sv, k->v_ref, k->keC);
    o[O_YZ] = y_z; o[O_YREF] = y_ref; o[O_E] = y_z - y_ref;

    /* the command for the period from t_{k+d}, and the plan for the one after */
    double raw, u_z, raw1, u_z1;
    if (k->kind == K_PI)
        pi_step(k, si_, sv, si2);
    k->ilim = 0;
    double r = law(k, i_p, v_p, u_p, P_load, P_in, P_in_dot, d, k->r_prev, &raw, &u_z);
    o[O_ILIM] = k->ilim ? 1.0 : 0.0;
    double plan = 0.0;
    if (k->plan) {
        double i1 = i_p, v1 = v_p, u1 = u_p;
        predict_in_range(&i1, &v1, &u1, P_load + Pdot * ((double)d + 0.5) * T, r, T, k->n_pred, R, L, C, u_min,
                         u_max);
        plan = law(k, i1, v1, u1, P_load, P_in, P_in_dot, d + 1, r, &raw1, &u_z1);
    }
    o[O_LIMITED] = (r != raw) ? 1.0 : 0.0;
    o[O_LATE] = late ? 1.0 : 0.0;
    o[O_DU_RAW] = raw;
    o[O_DU] = r;
    o[O_DU_NEXT] = plan;
    o[O_UZ] = u_z;
    memcpy(o + O_SEQ, &seq, sizeof seq);
    o[O_T] = t;
    k->r_prev = r;
    remember(k, seq, r, plan);
    o[O_STEPS] += 1.0;
    return took;
}

/* ------------------------------------------------------------------ Python type */

static int Kernel_init(Kernel *self, PyObject *args, PyObject *kw)
{
    (void)kw;
    double R, L, C, T, tau;
    int d, n_pred;
    if (!PyArg_ParseTuple(args, "dddddii", &R, &L, &C, &T, &tau, &d, &n_pred))
        return -1;
    if (d < 0 || n_pred < 1 || !(T > 0.0) || !(tau > 0.0)) {
        PyErr_SetString(PyExc_ValueError, "Kernel: need d >= 0, n_pred >= 1, T > 0, tau > 0");
        return -1;
    }
    PyMem_Free(self->pending);
    PyMem_Free(self->pending_seq);
    self->pending = PyMem_Calloc(2 * ((size_t)d + 1), sizeof(double));
    self->pending_seq = PyMem_Calloc((size_t)d + 1, sizeof(long long));
    if (self->pending == NULL || self->pending_seq == NULL) {
        PyErr_NoMemory();
        return -1;
    }
    self->R = R; self->L = L; self->C = C; self->T = T; self->tau = tau;
    self->d = d; self->n_pred = n_pred;
    memset(self->o, 0, sizeof(self->o));
    kernel_reset(self);
    return 0;
}

static void Kernel_dealloc(Kernel *self)
{
    PyMem_Free(self->pending);
    PyMem_Free(self->pending_seq);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyObject *Kernel_set_params(Kernel *self, PyObject *args)
{
    if (!PyArg_ParseTuple(args, "iiii(ddddd)(dd)(dddd)(dddd)dddi(dddd)(dddd)", &self->kind, &self->continuous,
                          &self->cancel_Et, &self->plan,
                          &self->v_ref, &self->K, &self->alpha, &self->phi, &self->decay, &self->lK1, &self->lK2,
                          &self->bK1, &self->bK2, &self->bK3, &self->bPi, &self->u_min, &self->u_max, &self->r_max,
                          &self->i_floor, &self->keC, &self->late_tol, &self->obs, &self->load_ref, &self->nK_P,
                          &self->nK_E, &self->i_max, &self->n_decay, &self->kp_i, &self->ki_i, &self->kp_v, &self->ki_v))
        return NULL;
    Py_RETURN_NONE;
}

static PyObject *Kernel_reset(Kernel *self, PyObject *Py_UNUSED(ignored))
{
    kernel_reset(self);
    Py_RETURN_NONE;
}

/* n float arguments of a METH_FASTCALL function into x; 0 with an exception set if they are not that */
int float_args(PyObject *const *args, Py_ssize_t nargs, int n, double *x, const char *usage)
{
    if (nargs != n) {
        PyErr_Format(PyExc_TypeError, "%s takes %d arguments", usage, n);
        return 0;
    }
    for (int j = 0; j < n; j++) {
        x[j] = PyFloat_AsDouble(args[j]);
        if (x[j] == -1.0 && PyErr_Occurred())
            return 0;
    }
    return 1;
}

static int seq_of(PyObject *a, long long *seq)
{
    if (PyFloat_Check(a)) {  /* as before: an integral float below 2^53, where it is exact */
        double x = PyFloat_AS_DOUBLE(a);
        if (!(x == floor(x) && fabs(x) < 9007199254740992.0)) {
            PyErr_Format(PyExc_ValueError, "seq: %R is not an integer below 2^53", a);
            return 0;
        }
        *seq = (long long)x;
        return 1;
    }
    PyObject *n = PyNumber_Index(a);
    if (n == NULL)
        return 0;
    int overflow;
    long long v = PyLong_AsLongLongAndOverflow(n, &overflow);
    Py_DECREF(n);
    if (v == -1 && PyErr_Occurred())
        return 0;
    if (overflow || v >= SEQ_MAX || v <= -SEQ_MAX) {
        PyErr_Format(PyExc_ValueError, "seq: %R is beyond +-2^62", a);
        return 0;
    }
    *seq = v;
    return 1;
}

int seq_float_args(PyObject *const *args, Py_ssize_t nargs, int n, long long *seq, double *x, const char *usage)
{
    if (nargs != n) {
        PyErr_Format(PyExc_TypeError, "%s takes %d arguments", usage, n);
        return 0;
    }
    if (!seq_of(args[0], seq))
        return 0;
    x[0] = 0.0;
    for (int j = 1; j < n; j++) {
        x[j] = PyFloat_AsDouble(args[j]);
        if (x[j] == -1.0 && PyErr_Occurred())
            return 0;
    }
    return 1;
}

/* step(seq, t, i, v, u, i_load, P_r_in, P_r_in_dot) -> bool (estimator took the sample) */
static PyObject *Kernel_step(Kernel *self, PyObject *const *args, Py_ssize_t nargs)
{
    double x[8];
    long long seq;
    if (!seq_float_args(args, nargs, 8, &seq, x, "step(seq, t, i, v, u, i_load, P_r_in, P_r_in_dot)"))
        return NULL;
    int took = kernel_step(self, seq, x[1], x[2], x[3], x[4], x[5], x[6], x[7]);
    return PyBool_FromLong(took);
}

/* The outgoing rates at the port after a step, for the daemon's tick: P_r_out_port as a new float (None before the
 * first estimate), and Qdot_r_out_port into *qdot (0 then). */
PyObject *port_rates(const double *o, double *qdot)
{
    if (o[O_HAS_EST] == 0.0) {
        *qdot = 0.0;
        Py_RETURN_NONE;
    }
    *qdot = o[O_EST + E_QROP];
    return PyFloat_FromDouble(o[O_EST + E_PROP]);
}

/* step_values(seq, t, i, v, u, i_load, P_r_in, P_r_in_dot) -> (du_dt, du_dt_next, limited, late, P_r_out_port or
 * None before the first estimate, Qdot_r_out_port): one step and what the daemon's tick uses of it, in one call */
static PyObject *Kernel_step_values(Kernel *self, PyObject *const *args, Py_ssize_t nargs)
{
    double x[8];
    long long seq;
    if (!seq_float_args(args, nargs, 8, &seq, x, "step_values(seq, t, i, v, u, i_load, P_r_in, P_r_in_dot)"))
        return NULL;
    kernel_step(self, seq, x[1], x[2], x[3], x[4], x[5], x[6], x[7]);
    const double *o = self->o;
    double qdot;
    PyObject *P_out = port_rates(o, &qdot);
    if (P_out == NULL)
        return NULL;
    return Py_BuildValue("ddOONd", o[O_DU], o[O_DU_NEXT], o[O_LIMITED] != 0.0 ? Py_True : Py_False,
                         o[O_LATE] != 0.0 ? Py_True : Py_False, P_out, qdot);
}

/* est_record() -> (E, p, E_t, y_z, y_z_balance, y_ref, eta, u_z, P_r_out_port, Qdot_r_out_port, z_out0, z_out1):
 * core.CoreBase.est_record, from the buffer in one call */
static PyObject *Kernel_est_record(Kernel *self, PyObject *Py_UNUSED(ignored))
{
    const double *o = self->o, *e = o + O_EST;
    return Py_BuildValue("(dddddddddddd)", e[E_E], e[E_P], e[E_ET], o[O_YZ], e[E_YZB], o[O_YREF], e[E_ETA], o[O_UZ],
                         e[E_PROP], e[E_QROP], o[O_Z0], o[O_Z1]);
}

/* interaction() -> (P_r_out_port, P_dot_r_out_port, Qdot_r_out_port, z_run0, z_run1): core.CoreBase.interaction */
static PyObject *Kernel_interaction(Kernel *self, PyObject *Py_UNUSED(ignored))
{
    const double *o = self->o, *e = o + O_EST, *fv = o + O_FITV, *fs = o + O_FITS;
    double P_dot = -(fs[1] * fv[2] + fv[1] * fs[2]);
    return Py_BuildValue("(ddddd)", e[E_PROP], P_dot, e[E_QROP], o[O_ZRUN0], o[O_ZRUN1]);
}

/* run(inputs, du_out, width=9, next_out=None): a whole replay segment without returning to Python. inputs holds
 * n rows of width >= 9 doubles, the first 9 (seq, t, i, v, u, i_load, P_r_in, P_r_in_dot, stepped) read; a row
 * with stepped == 0 is not given to the core and answers 0.0 with no plan (the daemon held: ControlCore.hold).
 * du_out (and next_out, if given: the planned du/dt) receive n doubles. */
static PyObject *Kernel_run(Kernel *self, PyObject *args)
{
    Py_buffer in, out, nxt = {0};
    int width = 9;
    if (!PyArg_ParseTuple(args, "y*w*|iw*", &in, &out, &width, &nxt))
        return NULL;
    PyObject *res = NULL;
    Py_ssize_t row = (Py_ssize_t)((width >= 9 ? width : 9) * sizeof(double));
    Py_ssize_t n = in.len / row;
    if (width < 9 || in.len != n * row || out.len != n * (Py_ssize_t)sizeof(double)
        || (nxt.obj != NULL && nxt.len != out.len)) {
        PyErr_SetString(PyExc_ValueError, "run(): inputs must be n x width (>= 9) doubles, du_out and next_out n "
                                          "doubles");
        goto done;
    }
    const double *x = (const double *)in.buf;
    for (Py_ssize_t j = 0; j < n; j++) {  /* seq in a double column: exact only as an integer below 2^53 */
        double s = x[j * width];
        if (!(s == floor(s) && fabs(s) < 9007199254740992.0)) {
            PyErr_Format(PyExc_ValueError, "run(): row %zd: seq is not an integer below 2^53", j);
            goto done;
        }
    }
    double *du = (double *)out.buf, *dn = nxt.obj != NULL ? (double *)nxt.buf : NULL;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t j = 0; j < n; j++, x += width) {
        if (x[8] != 0.0) {
            kernel_step(self, (long long)x[0], x[1], x[2], x[3], x[4], x[5], x[6], x[7]);
            du[j] = self->o[O_DU];
            if (dn != NULL)
                dn[j] = self->o[O_DU_NEXT];
        } else {
            remember(self, (long long)x[0], 0.0, 0.0);
            du[j] = 0.0;
            if (dn != NULL)
                dn[j] = 0.0;
        }
    }
    Py_END_ALLOW_THREADS
    res = Py_None;
    Py_INCREF(res);
done:
    PyBuffer_Release(&in);
    PyBuffer_Release(&out);
    if (nxt.obj != NULL)
        PyBuffer_Release(&nxt);
    return res;
}

static PyObject *Kernel_hold(Kernel *self, PyObject *args)
{
    PyObject *s;
    long long seq;
    double r = 0.0;
    if (!PyArg_ParseTuple(args, "O|d", &s, &r) || !seq_of(s, &seq))
        return NULL;
    remember(self, seq, r, 0.0);
    Py_RETURN_NONE;
}

static PyObject *Kernel_applied_rate(Kernel *self, PyObject *Py_UNUSED(ignored))
{
    if (self->d == 0)
        return PyFloat_FromDouble(self->r_prev);
    return PyFloat_FromDouble(issued(self, (self->o[O_STEPS] > 0.0 ? kernel_seq(self) + 1 : 0) - self->d));
}

/* The outputs, read-only; the view holds a reference to the kernel, which owns o[] for its whole life. */
static int Kernel_getbuffer(Kernel *self, Py_buffer *view, int flags)
{
    return PyBuffer_FillInfo(view, (PyObject *)self, self->o, sizeof(self->o), 1, flags);
}

static PyBufferProcs Kernel_as_buffer = {(getbufferproc)Kernel_getbuffer, NULL};

static PyMethodDef Kernel_methods[] = {
    {"set_params", (PyCFunction)Kernel_set_params, METH_VARARGS, "set gains and limits (see compiled.py)"},
    {"reset", (PyCFunction)Kernel_reset, METH_NOARGS, "forget history"},
    {"step", (PyCFunction)(void (*)(void))Kernel_step, METH_FASTCALL, "one control step"},
    {"step_values", (PyCFunction)(void (*)(void))Kernel_step_values, METH_FASTCALL,
     "one control step; (du_dt, du_dt_next, limited, late, P_r_out_port or None, Qdot_r_out_port)"},
    {"run", (PyCFunction)Kernel_run, METH_VARARGS, "many steps (replay)"},
    {"est_record", (PyCFunction)Kernel_est_record, METH_NOARGS, "the estimator record's values (CoreBase.est_record)"},
    {"interaction", (PyCFunction)Kernel_interaction, METH_NOARGS, "the outgoing interaction (CoreBase.interaction)"},
    {"applied_rate", (PyCFunction)Kernel_applied_rate, METH_NOARGS, "du/dt acting now"},
    {"hold", (PyCFunction)Kernel_hold, METH_VARARGS, "hold(seq, du_dt=0): seq was answered with du_dt, no plan"},
    {NULL, NULL, 0, NULL},
};

PyTypeObject KernelType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "service._kernel.Kernel",
    .tp_basicsize = sizeof(Kernel),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "Compiled ControlCore step; outputs in a read-only buffer of doubles (layout in compiled.py).",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Kernel_init,
    .tp_dealloc = (destructor)Kernel_dealloc,
    .tp_methods = Kernel_methods,
    .tp_as_buffer = &Kernel_as_buffer,
};
