/* ptlaw.h: the control law of pneutune (modified DARC, Qian et al. 2014, Eqs. 9-36, and its
 * variants original_darc, direct_diff and pid) as portable C99.
 *
 * It mirrors control/law/darc.py (step_into, init_state) operation by operation, on the same
 * flat vectors, with the indices of pt_layout.h (generated from the Python constants):
 *
 *   state[PT_STATE_SIZE]  controller state, caller-owned, updated in place by pt_step_into
 *   meas[PT_MEAS_SIZE]    t [s], x [m], p_a, p_b, p_s [Pa abs], x_r [m], v_r [m/s], a_r [m/s^2]
 *   cfg[PT_CFG_SIZE]      packed config (pneutune.control.law.layout.pack), read only
 *   duties_out[4]         commanded duties (0..1) of a_in, a_out, b_in, b_out
 *
 * No dynamic memory, no recursion, no global state; only <math.h>. pt_real is double unless
 * PT_REAL_FLOAT is defined (then float and the float math functions).
 *
 * Equality with the compiled numba step: with IEEE doubles evaluated in their own precision
 * (FLT_EVAL_METHOD 0, e.g. x86-64 SSE2 or AArch64), without floating-point contraction into
 * fused multiply-adds (GCC's default under -std=c99, pass -ffp-contract=off with -std=gnu*;
 * ptlaw.c turns it off for clang) and without -ffast-math, every operation is the one numba performs, in the same order, so the results
 * are bit for bit those of darc.step_into when atan and pow come from the same libm.
 */
#ifndef PTLAW_H
#define PTLAW_H

#include "pt_layout.h"

#ifdef PT_REAL_FLOAT
typedef float pt_real;
#else
typedef double pt_real;
#endif

#ifdef __cplusplus
extern "C" {
#endif

/* One controller step (darc.step_into): updates state, writes duties_out[0..3].
 * Returns the Eq. (33) case (1..5), or 0 when cfg[PT_CFG_LAYOUT] != PT_CFG_LAYOUT_ID (every
 * valve closed, state[PT_S_STATUS] = 1). A non-finite Q_Ld closes every valve (case 3). */
int pt_step_into(pt_real *state, const pt_real *meas, const pt_real *cfg, pt_real *duties_out);

/* The state at the start of a run (darc.init_state) for a packed cfg, the initial position
 * x0 [m] and chamber pressures p_a0, p_b0 [Pa abs]. Returns 0; returns 1 and leaves state
 * untouched when cfg has another layout (where init_state raises ValueError). */
int pt_init_state(pt_real *state, const pt_real *cfg, pt_real x0, pt_real p_a0, pt_real p_b0);

/* The kernels the step is made of, exported for the host's tests and its Python wrappers
 * (control/law/kalman.py, projection.py, duty.py); a target needs only the two above. */

/* Eq. (35): x <- A x, P <- A P A^T + W Q W^T for n states (row-major); work >= n*n + n. */
void pt_kf_predict_into(pt_real *x, pt_real *Pf, const pt_real *A, const pt_real *WQWt,
                        pt_real *work, int n);
/* Eq. (36) in Joseph form for a scalar z = H x + v, E[v^2] = R; work >= 2 n*n + n. */
void pt_kf_update_into(pt_real *x, pt_real *Pf, pt_real z, const pt_real *H, pt_real R,
                       pt_real *work, int n);
/* Eq. (10), elementwise; out may be v. */
void pt_proj_into(const pt_real *theta_hat, const pt_real *v, const pt_real *theta_min,
                  const pt_real *theta_max, pt_real *out, int n);
/* Eq. (11), elementwise; out may be v. */
void pt_sat_into(const pt_real *v, const pt_real *rate_max, pt_real *out, int n);
/* Eq. (9): out = sat(Proj(Gamma tau)). */
void pt_adaptation_rate_into(const pt_real *theta_hat, const pt_real *tau, const pt_real *gamma,
                             const pt_real *rate_max, const pt_real *theta_min,
                             const pt_real *theta_max, pt_real *out, int n);
/* theta <- clip(theta + Ts sat(Proj(Gamma tau))); rate_out the effective rate. */
void pt_adapt_step_into(pt_real *theta_hat, const pt_real *tau, const pt_real *gamma,
                        const pt_real *rate_max, const pt_real *theta_min,
                        const pt_real *theta_max, pt_real Ts, pt_real *rate_out, int n);
/* Q_L,F of Eq. (32) (corrected) for the mode of the sign of q_ld. */
pt_real pt_fully_open_q_l(pt_real q_ld, pt_real p_a, pt_real p_b, pt_real p_s, pt_real p0,
                          pt_real T0, pt_real nR, pt_real A_a, pt_real A_b, pt_real V_a,
                          pt_real V_b, const pt_real *C, const pt_real *b);
/* The five cases of Eq. (33) (corrected); returns the case 1..5. */
int pt_eq33_into(pt_real q_ld, pt_real q_lf, pt_real *u_out);
/* The smallest duty whose open fraction on the m-point curve reaches ratio. */
pt_real pt_pwm_inverse(pt_real ratio, const pt_real *duty_pts, const pt_real *ratio_pts, long m);
/* Eq. (33) then each valve's PWM inverse (valve i's curve from i * stride). */
int pt_duties_into(pt_real q_ld, pt_real q_lf, const pt_real *n_pts, const pt_real *duty_pts,
                   const pt_real *ratio_pts, long stride, pt_real *u_work, pt_real *duties_out);
/* Dead-zone dithering: a first-order sigma-delta per valve, once per PWM carrier period. */
void pt_dither_into(const pt_real *u, pt_real *duties, pt_real t, pt_real Ts, pt_real period,
                    const pt_real *d_k, const pt_real *r_k, pt_real *acc, pt_real *pulse,
                    pt_real *last);

/* The physics the law's model uses, as the plant's (control/physics/flow.py, friction.py):
 * the ISO 6358 flow of Eq. (7) [kg/s] and S_f of Eq. (4) with its derivative. */
pt_real pt_iso6358_flow(pt_real C, pt_real b, pt_real p_u, pt_real p_d, pt_real T_u);
pt_real pt_smooth_sign(pt_real v);
pt_real pt_smooth_sign_derivative(pt_real v);

#ifdef __cplusplus
}
#endif

#endif /* PTLAW_H */
