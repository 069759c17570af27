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

#ifdef __cplusplus
}
#endif

#endif /* PTLAW_H */
