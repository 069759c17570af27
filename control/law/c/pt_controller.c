/* pt_controller.c: the target's controller, law behind supervisor, in C99 (API and per-sample
 * order: pt_controller.h). It mirrors run_loop of control/rig/runtime.py, one sample per call.
 */
#include <math.h>
#include <stddef.h>
#include <stdint.h>

#include "pt_controller.h"

#ifdef PT_REAL_FLOAT
#define PT_C(x) x##f
#define PT_FABS fabsf
#else
#define PT_C(x) x
#define PT_FABS fabs
#endif

/* What a step returns after a fault or with an unusable config, and what it keeps. */
#define LATCHED (PT_FAULT_MASK | PT_STATUS_CONFIG_MASK)

/* The config bits cfg deserves: layouts of both vectors, fail-safe duties in [0, 1]. */
static uint32_t config_bits(const pt_config_t *cfg)
{
    int i;
    uint32_t bad = 0;
    if (cfg->law[PT_CFG_LAYOUT] != (pt_real)PT_CFG_LAYOUT_ID || !pt_sup_layout_ok(cfg->sup)) {
        bad |= PT_STATUS_BAD_LAYOUT;
    }
    for (i = 0; i < 4; ++i) {
        if (!(cfg->fail_safe[i] >= PT_C(0.0) && cfg->fail_safe[i] <= PT_C(1.0))) {
            bad |= PT_STATUS_BAD_FAIL_SAFE;
        }
    }
    return bad;
}

/* The duties of a stopped controller: the fail-safe, or every valve closed when the config is
 * unusable; the latched status. */
static uint32_t stopped(const pt_controller_t *c, const pt_config_t *cfg, pt_real *duties)
{
    int i;
    int usable = (c->status & PT_STATUS_CONFIG_MASK) == 0;
    for (i = 0; i < 4; ++i) {
        duties[i] = usable ? cfg->fail_safe[i] : PT_C(0.0);
    }
    return c->status & LATCHED;
}

int pt_controller_init(pt_controller_t *c, const pt_config_t *cfg, const pt_sensors_t *first)
{
    int i;
    c->status = config_bits(cfg);
    pt_sup_reset(c->sup);
    for (i = 0; i < PT_STATE_SIZE; ++i) {
        c->law[i] = PT_C(0.0);
    }
    if (c->status != 0) {
        return 1;
    }
    if (first != NULL && isfinite(first->x) && isfinite(first->p_a) && isfinite(first->p_b)) {
        pt_init_state(c->law, cfg->law, first->x, first->p_a, first->p_b);
        c->sup[PT_SUP_S_LAW_READY] = PT_C(1.0);
    }
    return 0;
}

uint32_t pt_controller_step_stamped(pt_controller_t *c, const pt_config_t *cfg,
                                    const pt_sensors_t *s, const pt_real *sample_times,
                                    const pt_reference_t *r, pt_real t, pt_real duties[4])
{
    pt_real v[4];
    pt_real meas[PT_MEAS_SIZE];
    uint32_t fault, warn;
    c->status |= config_bits(cfg);
    if (c->status & LATCHED) {
        return stopped(c, cfg, duties);
    }
    /* read, supervisor check (run_loop's _check_sample) */
    v[PT_CH_X] = s->x;
    v[PT_CH_P_A] = s->p_a;
    v[PT_CH_P_B] = s->p_b;
    v[PT_CH_P_S] = s->p_s;
    fault = pt_sup_check_sensors(c->sup, cfg->sup, t, v, sample_times);
    if (fault == 0 && c->sup[PT_SUP_S_FIRST_DONE] == PT_C(0.0)
        && !(PT_FABS(s->x - r->x_r) <= cfg->sup[PT_SUP_START_TOL])) {
        fault = PT_FAULT_START_POSITION;
        c->sup[PT_SUP_S_FAULT_CHANNEL] = (pt_real)PT_CH_X;
    }
    if (fault == 0 && !(isfinite(t) && isfinite(r->x_r) && isfinite(r->v_r)
                        && isfinite(r->a_r))) {
        fault = PT_FAULT_REFERENCE_NAN;
    }
    if (fault != 0) {
        c->status |= fault;
        return stopped(c, cfg, duties);
    }
    c->sup[PT_SUP_S_FIRST_DONE] = PT_C(1.0);
    /* the law's step, from init_state(x_r(0), p_a(0), p_b(0)) on the first sample */
    if (c->sup[PT_SUP_S_LAW_READY] == PT_C(0.0)) {
        pt_init_state(c->law, cfg->law, r->x_r, s->p_a, s->p_b);
        c->sup[PT_SUP_S_LAW_READY] = PT_C(1.0);
    }
    meas[PT_M_T] = t;
    meas[PT_M_X] = s->x;
    meas[PT_M_P_A] = s->p_a;
    meas[PT_M_P_B] = s->p_b;
    meas[PT_M_P_S] = s->p_s;
    meas[PT_M_X_R] = r->x_r;
    meas[PT_M_V_R] = r->v_r;
    meas[PT_M_A_R] = r->a_r;
    pt_step_into(c->law, meas, cfg->law, duties);
    /* the re-identification warnings on theta-hat after the step and the measured p_s */
    warn = pt_sup_check_estimates(c->sup, cfg->sup, t, s->p_s, c->law + PT_S_THETA);
    c->status |= warn;
    return (c->status & LATCHED) | warn;
}

uint32_t pt_controller_step(pt_controller_t *c, const pt_config_t *cfg, const pt_sensors_t *s,
                            const pt_reference_t *r, pt_real t, pt_real duties[4])
{
    return pt_controller_step_stamped(c, cfg, s, NULL, r, t, duties);
}

uint32_t pt_controller_trip(pt_controller_t *c, const pt_config_t *cfg, uint32_t fault,
                            pt_real duties[4])
{
    uint32_t bits = fault & PT_FAULT_MASK;
    c->status |= config_bits(cfg);
    if ((c->status & PT_FAULT_MASK) == 0) {
        c->status |= bits != 0 ? (bits & (~bits + 1u)) : PT_FAULT_RIG_IO;
    }
    return stopped(c, cfg, duties);
}
