/* ptlaw.c: the control law of pneutune in C99 (API and conventions: ptlaw.h).
 *
 * Each function below mirrors one numba function of control/law/ (and control/physics/),
 * named in its comment; expressions keep the Python's operands and evaluation order (C and
 * Python group + - * / alike, left to right), so every rounding is numba's.
 */
#include <math.h>

#include "ptlaw.h"

/* numba never fuses a*b + c into one fused multiply-add; neither may the C (an FMA rounds once
 * where numba rounds twice). GCC contracts only outside ISO mode (-std=gnu*, or
 * -ffp-contract=fast), and ignores this pragma with a warning, so it is for clang, whose default
 * contracts within an expression. */
#ifdef __clang__
#pragma STDC FP_CONTRACT OFF
#endif

#ifdef PT_REAL_FLOAT
#define PT_C(x) x##f
#define PT_ATAN atanf
#define PT_SQRT sqrtf
#define PT_FLOOR floorf
#define PT_FABS fabsf
#define PT_POW powf
#else
#define PT_C(x) x
#define PT_ATAN atan
#define PT_SQRT sqrt
#define PT_FLOOR floor
#define PT_FABS fabs
#define PT_POW pow
#endif

#define RHO0 ((pt_real)PT_RHO0)
#define T_REF ((pt_real)PT_T_REF)
#define LIN_WIDTH ((pt_real)PT_LIN_WIDTH)
#define SF_SLOPE ((pt_real)PT_SF_SLOPE)
#define PI ((pt_real)PT_PI)

/* The Kalman scratch at PT_S_WORK holds kalman.work_size(3) = 2 * 3 * 3 + 3 values (a
 * negative array size, a compile error, if pt_layout.h gives it less). */
typedef char pt_work_fits[(PT_STATE_SIZE - PT_S_WORK >= 2 * 3 * 3 + 3) ? 1 : -1];

/* A code of no enum: what code() gives for a value numba's int() cannot represent. */
#define NO_CODE (-1000000L)

/* int(v) of numba for an enum code read from cfg: truncation toward zero. numba converts a NaN
 * or an out-of-range value to INT64_MIN (x86), which equals no code; so does NO_CODE. */
static long code(pt_real v)
{
    if (!(v > PT_C(-1.0e5) && v < PT_C(1.0e5))) {
        return NO_CODE;
    }
    return (long)v;
}

/* --- control/physics/friction.py ------------------------------------------------------- */

/* smooth_sign: S_f of Eq. (4), (2/pi) atan(1000 v). */
static pt_real smooth_sign(pt_real v)
{
    return (PT_C(2.0) / PI) * PT_ATAN(SF_SLOPE * v);
}

/* smooth_sign_derivative: dS_f/dv of Eq. (4) [s/m]. */
static pt_real smooth_sign_derivative(pt_real v)
{
    pt_real z = SF_SLOPE * v;
    return (PT_C(2.0) / PI) * SF_SLOPE / (PT_C(1.0) + z * z);
}

/* --- control/physics/flow.py ----------------------------------------------------------- */

/* iso6358_flow: mass flow from p_u to p_d, Eq. (7), with the linear segment over the last
 * LIN_WIDTH of pressure ratio [kg/s], >= 0. */
static pt_real iso6358_flow(pt_real C, pt_real b, pt_real p_u, pt_real p_d, pt_real T_u)
{
    pt_real choked, r, one_b, s, s_lin;
    if (p_u <= PT_C(0.0) || p_d >= p_u) {
        return PT_C(0.0);
    }
    choked = C * RHO0 * p_u * PT_SQRT(T_REF / T_u);
    r = p_d / p_u;
    if (r <= b) {
        return choked;
    }
    one_b = PT_C(1.0) - b;
    if (r <= PT_C(1.0) - LIN_WIDTH) {
        s = (r - b) / one_b;
        return choked * PT_SQRT(PT_C(1.0) - s * s);
    }
    s_lin = (PT_C(1.0) - LIN_WIDTH - b) / one_b;
    return choked * PT_SQRT(PT_C(1.0) - s_lin * s_lin) * (PT_C(1.0) - r) / LIN_WIDTH;
}

/* --- control/law/kalman.py ------------------------------------------------------------- */

/* kf_predict_into: time update of Eq. (35) in place, x <- A x, P <- A P A^T + W Q W^T, for n
 * states; A and WQWt row-major n x n, Pf the covariance row-major; work >= n*n + n. */
static void kf_predict_into(pt_real *x, pt_real *Pf, const pt_real *A, const pt_real *WQWt,
                            pt_real *work, int n)
{
    int i, j, k;
    pt_real s;
    /* x <- A x (through the scratch: x is read while written) */
    for (i = 0; i < n; ++i) {
        s = PT_C(0.0);
        for (j = 0; j < n; ++j) {
            s += A[i * n + j] * x[j];
        }
        work[i] = s;
    }
    for (i = 0; i < n; ++i) {
        x[i] = work[i];
    }
    /* T = A P (n*n in work[n:]) */
    for (i = 0; i < n; ++i) {
        for (j = 0; j < n; ++j) {
            s = PT_C(0.0);
            for (k = 0; k < n; ++k) {
                s += A[i * n + k] * Pf[k * n + j];
            }
            work[n + i * n + j] = s;
        }
    }
    /* P <- T A^T + WQWt */
    for (i = 0; i < n; ++i) {
        for (j = 0; j < n; ++j) {
            s = WQWt[i * n + j];
            for (k = 0; k < n; ++k) {
                s += work[n + i * n + k] * A[j * n + k];
            }
            Pf[i * n + j] = s;
        }
    }
}

/* kf_update_into: measurement update of Eq. (36) in Joseph form, in place, for the scalar
 * measurement z = H x + v, E[v^2] = R; work >= 2 n*n + n, work[:n] = the gain K on return. */
static void kf_update_into(pt_real *x, pt_real *Pf, pt_real z, const pt_real *H, pt_real R,
                           pt_real *work, int n)
{
    int i, j, k;
    int m0 = n;
    int t0 = n + n * n;
    pt_real S, s, innov;
    /* K = P H^T / S, S = H P H^T + R (K in work[:n]) */
    S = R;
    for (i = 0; i < n; ++i) {
        s = PT_C(0.0);
        for (j = 0; j < n; ++j) {
            s += Pf[i * n + j] * H[j];
        }
        work[i] = s;
        S += H[i] * s;
    }
    innov = z;
    for (i = 0; i < n; ++i) {
        innov -= H[i] * x[i];
    }
    for (i = 0; i < n; ++i) {
        work[i] = work[i] / S;
        x[i] += work[i] * innov;
    }
    /* M = I - K H (work[n : n + n*n]); T = M P (work[n + n*n : n + 2 n*n]) */
    for (i = 0; i < n; ++i) {
        for (j = 0; j < n; ++j) {
            work[m0 + i * n + j] = (i == j ? PT_C(1.0) : PT_C(0.0)) - work[i] * H[j];
        }
    }
    for (i = 0; i < n; ++i) {
        for (j = 0; j < n; ++j) {
            s = PT_C(0.0);
            for (k = 0; k < n; ++k) {
                s += work[m0 + i * n + k] * Pf[k * n + j];
            }
            work[t0 + i * n + j] = s;
        }
    }
    /* P <- T M^T + K R K^T */
    for (i = 0; i < n; ++i) {
        for (j = 0; j < n; ++j) {
            s = work[i] * R * work[j];
            for (k = 0; k < n; ++k) {
                s += work[t0 + i * n + k] * work[m0 + j * n + k];
            }
            Pf[i * n + j] = s;
        }
    }
}

/* --- control/law/projection.py --------------------------------------------------------- */

/* proj_into: the discontinuous projection of Eq. (10), elementwise (= as >= / <=);
 * out may be v itself. */
static void proj_into(const pt_real *theta_hat, const pt_real *v, const pt_real *theta_min,
                      const pt_real *theta_max, pt_real *out, int n)
{
    int i;
    pt_real vi;
    for (i = 0; i < n; ++i) {
        vi = v[i];
        if ((theta_hat[i] >= theta_max[i] && vi > PT_C(0.0))
            || (theta_hat[i] <= theta_min[i] && vi < PT_C(0.0))) {
            out[i] = PT_C(0.0);
        } else {
            out[i] = vi;
        }
    }
}

/* sat_into: the rate saturation of Eq. (11), elementwise; out may be v itself. */
static void sat_into(const pt_real *v, const pt_real *rate_max, pt_real *out, int n)
{
    int i;
    pt_real vi, m;
    for (i = 0; i < n; ++i) {
        vi = v[i];
        m = rate_max[i];
        if (vi > m) {
            out[i] = m;
        } else if (vi < -m) {
            out[i] = -m;
        } else {
            out[i] = vi;
        }
    }
}

/* adaptation_rate_into: the adaptation law of Eq. (9), out = sat(Proj(Gamma tau)). */
static void adaptation_rate_into(const pt_real *theta_hat, const pt_real *tau, const pt_real *gamma,
                                 const pt_real *rate_max, const pt_real *theta_min,
                                 const pt_real *theta_max, pt_real *out, int n)
{
    int i;
    for (i = 0; i < n; ++i) {
        out[i] = gamma[i] * tau[i];
    }
    proj_into(theta_hat, out, theta_min, theta_max, out, n);
    sat_into(out, rate_max, out, n);
}

/* adapt_step_into: theta <- clip(theta + Ts sat(Proj(Gamma tau)), theta_min, theta_max);
 * rate_out receives the effective rate (theta_new - theta_old) / Ts. */
static void adapt_step_into(pt_real *theta_hat, const pt_real *tau, const pt_real *gamma,
                            const pt_real *rate_max, const pt_real *theta_min,
                            const pt_real *theta_max, pt_real Ts, pt_real *rate_out, int n)
{
    int i;
    pt_real old, new_;
    adaptation_rate_into(theta_hat, tau, gamma, rate_max, theta_min, theta_max, rate_out, n);
    for (i = 0; i < n; ++i) {
        old = theta_hat[i];
        new_ = old + Ts * rate_out[i];
        if (new_ > theta_max[i]) {
            new_ = theta_max[i];
        } else if (new_ < theta_min[i]) {
            new_ = theta_min[i];
        }
        theta_hat[i] = new_;
        rate_out[i] = (new_ - old) / Ts;
    }
}

/* --- control/law/duty.py --------------------------------------------------------------- */

/* fully_open_q_l: Q_L,F of Eq. (32) (corrected) for the mode of the sign of q_ld [N/s], with
 * C and b of a_in, a_out, b_in, b_out. */
static pt_real fully_open_q_l(pt_real q_ld, pt_real p_a, pt_real p_b, pt_real p_s, pt_real p0,
                              pt_real T0, pt_real nR, pt_real A_a, pt_real A_b, pt_real V_a,
                              pt_real V_b, const pt_real *C, const pt_real *b)
{
    pt_real m_a, m_b;
    if (q_ld > PT_C(0.0)) {
        m_a = iso6358_flow(C[0], b[0], p_s, p_a, T0);
        m_b = iso6358_flow(C[3], b[3], p_b, p0, T0);
    } else if (q_ld < PT_C(0.0)) {
        m_a = iso6358_flow(C[1], b[1], p_a, p0, T0);
        m_b = iso6358_flow(C[2], b[2], p_s, p_b, T0);
    } else {
        return PT_C(0.0);
    }
    return nR * T0 * (A_a * m_a / V_a + A_b * m_b / V_b);
}

/* eq33_into: the five cases of Eq. (33) (corrected), effective open fractions of the four
 * valves in u_out; returns the case 1..5 (a NaN q_ld is case 3, all closed). */
static int eq33_into(pt_real q_ld, pt_real q_lf, pt_real *u_out)
{
    int i;
    pt_real r, u;
    for (i = 0; i < 4; ++i) {
        u_out[i] = PT_C(0.0);
    }
    if (q_ld > PT_C(0.0)) {
        if (q_lf > PT_C(0.0)) {
            r = q_ld / q_lf;
            u = r > PT_C(1.0) ? PT_C(1.0) : r;
            u_out[0] = u;
            u_out[3] = u;
            return PT_CASE_A_FILL;
        }
        u_out[0] = PT_C(1.0);
        u_out[3] = PT_C(1.0);
        return PT_CASE_A_FILL_NO_FLOW;
    }
    if (q_ld < PT_C(0.0)) {
        if (q_lf > PT_C(0.0)) {
            r = -q_ld / q_lf;
            u = r > PT_C(1.0) ? PT_C(1.0) : r;
            u_out[1] = u;
            u_out[2] = u;
            return PT_CASE_B_FILL;
        }
        u_out[1] = PT_C(1.0);
        u_out[2] = PT_C(1.0);
        return PT_CASE_B_FILL_NO_FLOW;
    }
    return PT_CASE_CLOSED;
}

/* pwm_inverse: the smallest duty whose effective open fraction on the curve
 * (duty_pts[:m], ratio_pts[:m]) reaches ratio: 0 for ratio <= 0, 1 at or above the top. */
static pt_real pwm_inverse(pt_real ratio, const pt_real *duty_pts, const pt_real *ratio_pts, long m)
{
    long i;
    pt_real top, r0, r1, d0, d1;
    if (!(ratio > PT_C(0.0))) {
        return PT_C(0.0);
    }
    if (m < 1) {
        /* no curve: pack writes 2..PT_PWM_MAX_POINTS points; numba would read outside its
         * empty slice here, the C closes the valve */
        return PT_C(0.0);
    }
    top = ratio_pts[m - 1];
    if (!(top > PT_C(0.0))) {
        return PT_C(0.0);
    }
    if (ratio >= top) {
        return PT_C(1.0);
    }
    for (i = 1; i < m; ++i) {
        r1 = ratio_pts[i];
        if (r1 >= ratio) {
            r0 = ratio_pts[i - 1];
            d0 = duty_pts[i - 1];
            d1 = duty_pts[i];
            if (r1 == ratio) {
                return d1;
            }
            return d0 + (ratio - r0) / (r1 - r0) * (d1 - d0);
        }
    }
    return duty_pts[m - 1];
}

/* duties_into: Eq. (33) then each valve's PWM inverse on its own curve (valve i's from
 * i * stride in duty_pts, ratio_pts, 4 * stride long); u_work receives the fractions. */
static int duties_into(pt_real q_ld, pt_real q_lf, const pt_real *n_pts, const pt_real *duty_pts,
                       const pt_real *ratio_pts, long stride, pt_real *u_work, pt_real *duties_out)
{
    int i;
    long at, avail, m;
    pt_real v;
    int c = eq33_into(q_ld, q_lf, u_work);
    for (i = 0; i < 4; ++i) {
        at = i * stride;
        avail = 4 * stride - at;
        /* int(n_pts[i]), as numba's slice [at:at + m] clamps it to the curves' array */
        v = n_pts[i];
        if (v >= (pt_real)avail) {
            m = avail;
        } else if (v >= PT_C(1.0)) {
            m = (long)v;
        } else {
            m = 0;
        }
        duties_out[i] = pwm_inverse(u_work[i], duty_pts + at, ratio_pts + at, m);
    }
    return c;
}

/* dither_into: dead-zone dithering, a first-order sigma-delta per valve deciding once per PWM
 * carrier period whether a valve with 0 < u < r_k gets the knee's pulse d_k or 0. */
static void dither_into(const pt_real *u, pt_real *duties, pt_real t, pt_real Ts, pt_real period,
                        const pt_real *d_k, const pt_real *r_k, pt_real *acc, pt_real *pulse,
                        pt_real *last)
{
    int i;
    pt_real ui, rk;
    pt_real n_next = PT_FLOOR((t + Ts) / period - PT_C(1.0e-9));
    pt_real m = n_next - last[0];
    if (m > PT_C(0.0)) {
        if (last[0] < PT_C(0.0)) {
            m = PT_C(1.0); /* the first decision (init_state set acc as after a closed valve) */
        }
        last[0] = n_next;
        for (i = 0; i < 4; ++i) {
            ui = u[i];
            rk = r_k[i];
            if (!(rk > PT_C(0.0))) {
                continue;
            }
            if (!(ui > PT_C(0.0))) {
                acc[i] = PT_C(0.5) * rk;
                pulse[i] = PT_C(0.0);
            } else if (ui >= rk) {
                pulse[i] = PT_C(1.0);
            } else {
                acc[i] += m * ui;
                if (acc[i] >= PT_C(0.5) * m * rk) {
                    pulse[i] = PT_C(1.0);
                    acc[i] -= m * rk;
                } else {
                    pulse[i] = PT_C(0.0);
                }
            }
        }
    }
    for (i = 0; i < 4; ++i) {
        ui = u[i];
        if (ui > PT_C(0.0) && ui < r_k[i]) {
            duties[i] = pulse[i] > PT_C(0.5) ? d_k[i] : PT_C(0.0);
        }
    }
}

/* --- control/law/darc.py --------------------------------------------------------------- */

/* Python's max(a, b) and min(a, b) as numba compiles them: the later argument replaces the
 * earlier only when strictly greater (smaller), so a NaN in first place is kept and a NaN in
 * second place is dropped. */
static pt_real py_max(pt_real a, pt_real b)
{
    return b > a ? b : a;
}

static pt_real py_min(pt_real a, pt_real b)
{
    return b < a ? b : a;
}

int pt_step_into(pt_real *state, const pt_real *meas, const pt_real *cfg, pt_real *duties_out)
{
    int i, first, c;
    long variant;
    pt_real Ts, x_meas, p_a, p_b, p_s, x_r, v_r, a_r;
    pt_real x1, x2, A_a, A_b, x_min, x_max, xc, V_a, V_b, F_p;
    pt_real k1, e1, e2, dx2eq, F_pd, e3, dF_pd, q_ld, q_lf;
    pt_real integral, i_max;
    pt_real th1, th2, th3, th4, th5, th6, sf, kappa2, kappa3, r2e2, r3e3, R_f;
    pt_real j_r, dsf, dF_dx1, dF_dx2, dx2, dF_dt, dF_dth, n, q_lda;
    pt_real *work, *mx, *mp, *theta, *tau, *thdot, *fx, *fp;

    if (cfg[PT_CFG_LAYOUT] != (pt_real)PT_CFG_LAYOUT_ID) {
        for (i = 0; i < 4; ++i) {
            duties_out[i] = PT_C(0.0);
        }
        state[PT_S_STATUS] = PT_C(1.0);
        return 0;
    }
    variant = code(cfg[PT_CFG_VARIANT]);
    first = state[PT_S_N_STEPS] == PT_C(0.0);
    Ts = cfg[PT_CFG_TS];
    x_meas = meas[PT_M_X];
    p_a = meas[PT_M_P_A];
    p_b = meas[PT_M_P_B];
    p_s = meas[PT_M_P_S];
    x_r = meas[PT_M_X_R];
    v_r = meas[PT_M_V_R];
    a_r = meas[PT_M_A_R];
    work = state + PT_S_WORK;

    /* 1. motion filter, Eqs. (34)-(36) */
    mx = state + PT_S_MX;
    mp = state + PT_S_MP;
    kf_predict_into(mx, mp, cfg + PT_CFG_KM_A, cfg + PT_CFG_KM_WQW, work, 3);
    kf_update_into(mx, mp, x_meas, cfg + PT_CFG_KM_H, cfg[PT_CFG_KM_R], work, 3);
    x1 = code(cfg[PT_CFG_POS_FB]) == PT_POS_FB_FILTERED ? mx[0] : x_meas;
    x2 = mx[1];

    A_a = cfg[PT_CFG_A_A];
    A_b = cfg[PT_CFG_A_B];
    x_min = cfg[PT_CFG_X_MIN];
    x_max = cfg[PT_CFG_X_MAX];
    xc = py_min(py_max(x1, x_min), x_max);
    V_a = cfg[PT_CFG_V0A] + A_a * (xc - x_min); /* Eq. (6) */
    V_b = cfg[PT_CFG_V0B] + A_b * (x_max - xc);
    F_p = A_a * p_a - A_b * p_b - cfg[PT_CFG_P0] * cfg[PT_CFG_A_R];

    /* 2. step 1, Eqs. (13)-(17), (20) */
    k1 = cfg[PT_CFG_K1];
    e1 = x1 - x_r;
    e2 = x2 - (v_r - k1 * e1);
    dx2eq = a_r - k1 * (x2 - v_r);

    theta = state + PT_S_THETA;
    tau = state + PT_S_TAU;
    thdot = state + PT_S_THETA_DOT;
    F_pd = PT_C(0.0);
    e3 = PT_C(0.0);
    dF_pd = PT_C(0.0);
    if (variant == PT_VARIANT_PID) {
        integral = state[PT_S_PID_I] + Ts * e1;
        i_max = cfg[PT_CFG_PID_IMAX];
        integral = py_min(py_max(integral, -i_max), i_max);
        state[PT_S_PID_I] = integral;
        q_ld = -(cfg[PT_CFG_PID_KP] * e1 + cfg[PT_CFG_PID_KI] * integral
                 + cfg[PT_CFG_PID_KD] * (x2 - v_r));
        for (i = 0; i < 6; ++i) {
            tau[i] = PT_C(0.0);
            thdot[i] = PT_C(0.0);
        }
    } else {
        /* the control of this step uses theta from before the update */
        th1 = theta[0];
        th2 = theta[1];
        th3 = theta[2];
        th4 = theta[3];
        th5 = theta[4];
        th6 = theta[5];
        sf = smooth_sign(x2);
        kappa2 = cfg[PT_CFG_K2] + cfg[PT_CFG_H2] * cfg[PT_CFG_H2] / (PT_C(4.0) * cfg[PT_CFG_EPS2]);
        F_pd = -th2 + th3 * x2 + th4 * sf + th1 * dx2eq - kappa2 * e2;
        e3 = F_p - F_pd;

        /* 4. adaptation, Eqs. (9)-(11), (17), (26); only while |v_r| > min_ref_speed */
        r2e2 = cfg[PT_CFG_R2] * e2;
        r3e3 = cfg[PT_CFG_R3] * e3;
        tau[0] = -dx2eq * r2e2;
        tau[1] = r2e2;
        tau[2] = -x2 * r2e2;
        tau[3] = -sf * r2e2;
        tau[4] = A_a * r3e3;
        tau[5] = -A_b * r3e3;
        if (PT_FABS(v_r) > cfg[PT_CFG_MIN_REF_SPEED]) {
            adapt_step_into(theta, tau, cfg + PT_CFG_GAMMA, cfg + PT_CFG_RATE_MAX,
                            cfg + PT_CFG_THETA_MIN, cfg + PT_CFG_THETA_MAX, Ts, thdot, 6);
        } else {
            for (i = 0; i < 6; ++i) {
                thdot[i] = PT_C(0.0);
            }
        }

        /* 5. dF_pd/dt */
        if (variant == PT_VARIANT_MODIFIED_DARC) {
            fx = state + PT_S_FX;
            fp = state + PT_S_FP;
            if (first) {
                R_f = cfg[PT_CFG_KF_R];
                fx[0] = F_pd;
                fx[1] = PT_C(0.0);
                fp[0] = R_f;
                fp[1] = PT_C(0.0);
                fp[2] = PT_C(0.0);
                fp[3] = R_f / (Ts * Ts);
            } else {
                kf_predict_into(fx, fp, cfg + PT_CFG_KF_A, cfg + PT_CFG_KF_WQW, work, 2);
                kf_update_into(fx, fp, F_pd, cfg + PT_CFG_KF_H, cfg[PT_CFG_KF_R], work, 2);
            }
            dF_pd = fx[1];
        } else if (variant == PT_VARIANT_DIRECT_DIFF) {
            dF_pd = first ? PT_C(0.0) : (F_pd - state[PT_S_F_PD_PREV]) / Ts;
        } else if (variant == PT_VARIANT_ORIGINAL_DARC) {
            j_r = first ? PT_C(0.0) : (a_r - state[PT_S_A_R_PREV]) / Ts;
            dsf = smooth_sign_derivative(x2);
            dF_dx1 = -kappa2 * k1;
            dF_dx2 = th3 + th4 * dsf - th1 * k1 - kappa2;
            if (code(cfg[PT_CFG_ORIG_ACCEL]) == PT_ORIG_ACCEL_MODEL) {
                dx2 = (F_p + th2 - th3 * x2 - th4 * sf) / th1;
            } else {
                dx2 = mx[2];
            }
            dF_dt = th1 * (j_r + k1 * a_r) + kappa2 * (a_r + k1 * v_r);
            dF_dth = dx2eq * thdot[0] - thdot[1] + x2 * thdot[2] + sf * thdot[3];
            dF_pd = dF_dx1 * x2 + dF_dx2 * dx2 + dF_dt + dF_dth;
        }

        /* 6. step 2, Eqs. (26), (29) */
        n = cfg[PT_CFG_N];
        q_lda = (-e2 * cfg[PT_CFG_R2] / cfg[PT_CFG_R3] + n * A_a * A_a * x2 * p_a / V_a
                 + n * A_b * A_b * x2 * p_b / V_b - A_a * th5 + A_b * th6 + dF_pd);
        kappa3 = cfg[PT_CFG_K3] + cfg[PT_CFG_H3] * cfg[PT_CFG_H3] / (PT_C(4.0) * cfg[PT_CFG_EPS3]);
        q_ld = q_lda - kappa3 * e3;
    }

    /* 7. step 3, Eqs. (32)-(33) and the PWM inverse */
    q_lf = fully_open_q_l(q_ld, p_a, p_b, p_s, cfg[PT_CFG_P0], cfg[PT_CFG_T0], cfg[PT_CFG_NR],
                          A_a, A_b, V_a, V_b, cfg + PT_CFG_VALVE_C, cfg + PT_CFG_VALVE_B);
    c = duties_into(q_ld, q_lf, cfg + PT_CFG_PWM_N, cfg + PT_CFG_PWM_DUTY, cfg + PT_CFG_PWM_RATIO,
                    PT_PWM_STRIDE, state + PT_S_U, duties_out);
    if (code(cfg[PT_CFG_DZ_MODE]) == PT_DZ_DITHER) {
        dither_into(state + PT_S_U, duties_out, meas[PT_M_T], Ts, cfg[PT_CFG_PWM_PERIOD],
                    cfg + PT_CFG_DZ_DUTY, cfg + PT_CFG_DZ_RATIO, state + PT_S_DZ_ACC,
                    state + PT_S_DZ_PULSE, state + PT_S_DZ_PERIOD);
    }

    state[PT_S_F_PD_PREV] = F_pd;
    state[PT_S_A_R_PREV] = a_r;
    state[PT_S_N_STEPS] += PT_C(1.0);
    state[PT_S_STATUS] = PT_C(0.0);
    state[PT_S_E1] = e1;
    state[PT_S_E2] = e2;
    state[PT_S_E3] = e3;
    state[PT_S_X_HAT] = mx[0];
    state[PT_S_V_HAT] = mx[1];
    state[PT_S_A_HAT] = mx[2];
    state[PT_S_F_PD] = F_pd;
    state[PT_S_DF_PD] = dF_pd;
    state[PT_S_Q_LD] = q_ld;
    state[PT_S_Q_LF] = q_lf;
    state[PT_S_CASE] = (pt_real)c;
    state[PT_S_F_P] = F_p;
    return c;
}

int pt_init_state(pt_real *state, const pt_real *cfg, pt_real x0, pt_real p_a0, pt_real p_b0)
{
    int i;
    pt_real Ts, R, F_p0;
    /* init_state computes Ts**2 and Ts**4 with numpy's float64 power, which is libm's pow (not
     * always Ts*Ts rounded once); the volatile exponents keep the compiler from rewriting
     * pow(Ts, 2) as Ts*Ts. */
    volatile pt_real two = PT_C(2.0);
    volatile pt_real four = PT_C(4.0);
    if (cfg[PT_CFG_LAYOUT] != (pt_real)PT_CFG_LAYOUT_ID) {
        return 1;
    }
    for (i = 0; i < PT_STATE_SIZE; ++i) {
        state[i] = PT_C(0.0);
    }
    for (i = 0; i < 6; ++i) {
        state[PT_S_THETA + i] = cfg[PT_CFG_THETA_0 + i];
    }
    Ts = cfg[PT_CFG_TS];
    R = cfg[PT_CFG_KM_R];
    state[PT_S_MX + 0] = x0;
    state[PT_S_MX + 1] = PT_C(0.0);
    state[PT_S_MX + 2] = PT_C(0.0);
    /* P0 = diag(R, R/Ts^2, R/Ts^4) */
    state[PT_S_MP + 0] = R;
    state[PT_S_MP + 4] = R / PT_POW(Ts, two);
    state[PT_S_MP + 8] = R / PT_POW(Ts, four);
    F_p0 = cfg[PT_CFG_A_A] * p_a0 - cfg[PT_CFG_A_B] * p_b0 - cfg[PT_CFG_P0] * cfg[PT_CFG_A_R];
    state[PT_S_FX] = F_p0;
    state[PT_S_F_P] = F_p0;
    state[PT_S_F_PD] = F_p0;
    state[PT_S_F_PD_PREV] = F_p0;
    state[PT_S_X_HAT] = x0;
    for (i = 0; i < 4; ++i) { /* as after a closed valve */
        state[PT_S_DZ_ACC + i] = PT_C(0.5) * cfg[PT_CFG_DZ_RATIO + i];
    }
    state[PT_S_DZ_PERIOD] = PT_C(-1.0);
    return 0;
}

/* --- exported kernels ----------------------------------------------------------------
 * The step calls the static functions above; these are their exported names (ptlaw.h), so
 * that no other library loaded in the same process can interpose on the step's own calls. */

void pt_kf_predict_into(pt_real *x, pt_real *Pf, const pt_real *A, const pt_real *WQWt,
                        pt_real *work, int n)
{
    kf_predict_into(x, Pf, A, WQWt, work, n);
}

void pt_kf_update_into(pt_real *x, pt_real *Pf, pt_real z, const pt_real *H, pt_real R,
                       pt_real *work, int n)
{
    kf_update_into(x, Pf, z, H, R, work, n);
}

void pt_proj_into(const pt_real *theta_hat, const pt_real *v, const pt_real *theta_min,
                  const pt_real *theta_max, pt_real *out, int n)
{
    proj_into(theta_hat, v, theta_min, theta_max, out, n);
}

void pt_sat_into(const pt_real *v, const pt_real *rate_max, pt_real *out, int n)
{
    sat_into(v, rate_max, out, n);
}

void pt_adaptation_rate_into(const pt_real *theta_hat, const pt_real *tau, const pt_real *gamma,
                             const pt_real *rate_max, const pt_real *theta_min,
                             const pt_real *theta_max, pt_real *out, int n)
{
    adaptation_rate_into(theta_hat, tau, gamma, rate_max, theta_min, theta_max, out, n);
}

void pt_adapt_step_into(pt_real *theta_hat, const pt_real *tau, const pt_real *gamma,
                        const pt_real *rate_max, const pt_real *theta_min,
                        const pt_real *theta_max, pt_real Ts, pt_real *rate_out, int n)
{
    adapt_step_into(theta_hat, tau, gamma, rate_max, theta_min, theta_max, Ts, rate_out, n);
}

pt_real pt_fully_open_q_l(pt_real q_ld, pt_real p_a, pt_real p_b, pt_real p_s, pt_real p0,
                          pt_real T0, pt_real nR, pt_real A_a, pt_real A_b, pt_real V_a,
                          pt_real V_b, const pt_real *C, const pt_real *b)
{
    return fully_open_q_l(q_ld, p_a, p_b, p_s, p0, T0, nR, A_a, A_b, V_a, V_b, C, b);
}

int pt_eq33_into(pt_real q_ld, pt_real q_lf, pt_real *u_out)
{
    return eq33_into(q_ld, q_lf, u_out);
}

pt_real pt_pwm_inverse(pt_real ratio, const pt_real *duty_pts, const pt_real *ratio_pts, long m)
{
    return pwm_inverse(ratio, duty_pts, ratio_pts, m);
}

int pt_duties_into(pt_real q_ld, pt_real q_lf, const pt_real *n_pts, const pt_real *duty_pts,
                   const pt_real *ratio_pts, long stride, pt_real *u_work, pt_real *duties_out)
{
    return duties_into(q_ld, q_lf, n_pts, duty_pts, ratio_pts, stride, u_work, duties_out);
}

void pt_dither_into(const pt_real *u, pt_real *duties, pt_real t, pt_real Ts, pt_real period,
                    const pt_real *d_k, const pt_real *r_k, pt_real *acc, pt_real *pulse,
                    pt_real *last)
{
    dither_into(u, duties, t, Ts, period, d_k, r_k, acc, pulse, last);
}

pt_real pt_iso6358_flow(pt_real C, pt_real b, pt_real p_u, pt_real p_d, pt_real T_u)
{
    return iso6358_flow(C, b, p_u, p_d, T_u);
}

pt_real pt_smooth_sign(pt_real v)
{
    return smooth_sign(v);
}

pt_real pt_smooth_sign_derivative(pt_real v)
{
    return smooth_sign_derivative(v);
}
