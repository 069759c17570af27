/* pt_supervisor.c: the safety supervisor in C99 (API and conventions: pt_supervisor.h).
 *
 * The rules are those control/rig/supervisor.py states (its module docstring), checked in that
 * order; each function is what a method of its Supervisor class calls, named in its comment.
 * The memory is the state vector: 0/1 flags and the times they were set.
 */
#include <math.h>
#include <stddef.h>
#include <stdint.h>

#include "pt_supervisor.h"

#ifdef PT_REAL_FLOAT
#define PT_C(x) x##f
#define PT_FABS fabsf
#else
#define PT_C(x) x
#define PT_FABS fabs
#endif

/* Supervisor.reset */
void pt_sup_reset(pt_real *state)
{
    int i;
    for (i = 0; i < PT_SUP_STATE_SIZE; ++i) {
        state[i] = PT_C(0.0);
    }
    state[PT_SUP_S_FAULT_CHANNEL] = PT_C(-1.0);
}

int pt_sup_layout_ok(const pt_real *sup)
{
    return sup[PT_SUP_LAYOUT] == (pt_real)PT_SUP_LAYOUT_ID;
}

/* A fault found on channel ch (-1: not a channel's): its bit, the channel kept. */
static uint32_t found(pt_real *state, uint32_t bit, int ch)
{
    state[PT_SUP_S_FAULT_CHANNEL] = (pt_real)ch;
    return bit;
}

/* Supervisor._stale: the first stale channel, -1 for none. */
static int stale_channel(pt_real *state, const pt_real *sup, pt_real t, const pt_real *v,
                         const pt_real *sample_times)
{
    int i;
    int first = -1;
    int started = state[PT_SUP_S_STARTED] != PT_C(0.0);
    pt_real limit = sup[PT_SUP_STALE_AGE];
    if (sample_times != NULL) {
        /* the first channel older than the limit, in channel order; a NaN sample time
           (the rig says the channel never delivered) is older than any limit */
        for (i = 0; i < 4; ++i) {
            if (!(t - sample_times[i] <= limit)) {
                return i;
            }
        }
        return -1;
    }
    for (i = 0; i < 4; ++i) {
        if (v[i] != state[PT_SUP_S_LAST + i] || !started) {
            state[PT_SUP_S_LAST + i] = v[i];
            state[PT_SUP_S_CHANGED_AT + i] = t;
        } else if (i > 0 && sup[PT_SUP_FREEZE] != PT_C(0.0) && first < 0) {
            if (t - state[PT_SUP_S_CHANGED_AT + i] > limit) {
                first = i;
            }
        }
    }
    state[PT_SUP_S_STARTED] = PT_C(1.0);
    return first;
}

/* Supervisor.check_sensors */
uint32_t pt_sup_check_sensors(pt_real *state, const pt_real *sup, pt_real t,
                              const pt_real *sensors, const pt_real *sample_times)
{
    int i;
    pt_real x = sensors[PT_CH_X];
    if (!pt_sup_layout_ok(sup)) {
        return PT_STATUS_BAD_LAYOUT;
    }
    state[PT_SUP_S_FAULT_CHANNEL] = PT_C(-1.0);
    for (i = 0; i < 4; ++i) {
        if (!isfinite(sensors[i])) {
            return found(state, PT_FAULT_SENSOR_NAN, i);
        }
    }
    if (!(sup[PT_SUP_X_SPAN_LO] <= x && x <= sup[PT_SUP_X_SPAN_HI])) {
        return found(state, PT_FAULT_SENSOR_RANGE, PT_CH_X);
    }
    for (i = 1; i < 4; ++i) {
        if (!(sup[PT_SUP_P_SENSOR_LO] <= sensors[i] && sensors[i] <= sup[PT_SUP_P_SENSOR_HI])) {
            return found(state, PT_FAULT_SENSOR_RANGE, i);
        }
    }
    i = stale_channel(state, sup, t, sensors, sample_times);
    if (i >= 0) {
        return found(state, PT_FAULT_SENSOR_STALE, i);
    }
    if (!(sup[PT_SUP_X_LIM_LO] <= x && x <= sup[PT_SUP_X_LIM_HI])) {
        return found(state, PT_FAULT_POSITION_LIMIT, PT_CH_X);
    }
    for (i = 1; i < 3; ++i) {
        if (sensors[i] > sup[PT_SUP_P_MAX]) {
            return found(state, PT_FAULT_OVERPRESSURE, i);
        }
    }
    if (sensors[PT_CH_P_S] < sup[PT_SUP_SUPPLY_MIN]) {
        return found(state, PT_FAULT_SUPPLY_LOSS, PT_CH_P_S);
    }
    return 0;
}

/* Supervisor.check_estimates */
uint32_t pt_sup_check_estimates(pt_real *state, const pt_real *sup, pt_real t, pt_real p_s,
                                const pt_real *theta)
{
    static const int watched[PT_SUP_N_WATCHED] = PT_SUP_WATCHED_THETA_INIT;
    uint32_t out = 0;
    int j, side, k, near;
    pt_real th;
    if (!pt_sup_layout_ok(sup)) {
        return PT_STATUS_BAD_LAYOUT;
    }
    if (PT_FABS(p_s - sup[PT_SUP_P_S_MODEL]) > sup[PT_SUP_SUPPLY_WARN_DELTA]) {
        if (state[PT_SUP_S_SUPPLY_OFF] == PT_C(0.0)) {
            state[PT_SUP_S_SUPPLY_OFF] = PT_C(1.0);
            state[PT_SUP_S_SUPPLY_SINCE] = t;
        }
        if (t - state[PT_SUP_S_SUPPLY_SINCE] >= sup[PT_SUP_SUPPLY_HOLD]
            && state[PT_SUP_S_WARNED_SUPPLY] == PT_C(0.0)) {
            state[PT_SUP_S_WARNED_SUPPLY] = PT_C(1.0);
            out |= PT_WARN_REIDENTIFY_SUPPLY;
        }
    } else {
        state[PT_SUP_S_SUPPLY_OFF] = PT_C(0.0);
    }
    for (j = 0; j < PT_SUP_N_WATCHED; ++j) {
        th = theta[watched[j]];
        for (side = 0; side < 2; ++side) {
            k = 2 * j + side;
            near = side == 0 ? th <= sup[PT_SUP_THETA_NEAR_LO + j]
                             : th >= sup[PT_SUP_THETA_NEAR_HI + j];
            if (!near) {
                state[PT_SUP_S_THETA_NEAR + k] = PT_C(0.0);
                continue;
            }
            if (state[PT_SUP_S_THETA_NEAR + k] == PT_C(0.0)) {
                state[PT_SUP_S_THETA_NEAR + k] = PT_C(1.0);
                state[PT_SUP_S_THETA_SINCE + k] = t;
            }
            if (t - state[PT_SUP_S_THETA_SINCE + k] >= sup[PT_SUP_THETA_HOLD]
                && state[PT_SUP_S_WARNED_THETA + k] == PT_C(0.0)) {
                state[PT_SUP_S_WARNED_THETA + k] = PT_C(1.0);
                out |= PT_WARN_REIDENTIFY_THETA | ((uint32_t)1 << (PT_WARN_THETA_BIT0 + k));
            }
        }
    }
    return out;
}

int pt_first_fault(uint32_t status)
{
    int i;
    for (i = 0; i < PT_FAULT_COUNT; ++i) {
        if (status & ((uint32_t)1 << i)) {
            return i;
        }
    }
    return -1;
}

const char *pt_fault_name(int index)
{
    static const char *const names[PT_FAULT_COUNT] = PT_FAULT_NAMES_INIT;
    if (index < 0 || index >= PT_FAULT_COUNT) {
        return "";
    }
    return names[index];
}
