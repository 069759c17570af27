/* pt_supervisor.h: the safety supervisor of pneutune's deploy runtime as portable C99: the
 * runtime calls it through ctypes (control/rig/supervisor.py, class Supervisor, which holds the
 * rules' description and formats the events), and targets that run the control law (ptlaw.h)
 * from a timer interrupt call it around the law. Flat vectors, indices in pt_sup_layout.h
 * (generated from control/rig/supervisor_pack.py):
 *
 *   sup[PT_SUP_SIZE]          settings (supervisor_pack.pack_supervisor), read only: the
 *                             thresholds precomputed in double exactly as the Python compares
 *   state[PT_SUP_STATE_SIZE]  memory, caller-owned; pt_sup_reset at the start of a run
 *   sensors[4]                x [m], p_a, p_b, p_s [Pa abs] (PT_CH_*, supervisor.CHANNELS)
 *   sample_times[4]           optional: the time each channel was last refreshed [s], on the
 *                             clock of t; NULL when the target cannot tell
 *
 * Faults (pt_sup_check_sensors, before the control step), checked in the Python order; the
 * first one found is returned as its single bit (PT_FAULT_*), 0 when the sample is fit:
 *   PT_FAULT_SENSOR_NAN      a reading is NaN or infinite
 *   PT_FAULT_SENSOR_RANGE    x outside [PT_SUP_X_SPAN_LO, PT_SUP_X_SPAN_HI], a pressure outside
 *                            [PT_SUP_P_SENSOR_LO, PT_SUP_P_SENSOR_HI]
 *   PT_FAULT_SENSOR_STALE    with sample_times: t - sample_times[i] > PT_SUP_STALE_AGE for a
 *                            channel; without: a pressure channel whose reading repeated bit for
 *                            bit (==) for longer than that (when PT_SUP_FREEZE is 1). The
 *                            position is never judged on its values (it is quantised, a piston
 *                            at rest repeats its count): only sample_times catch a frozen x.
 *   PT_FAULT_POSITION_LIMIT  x outside [PT_SUP_X_LIM_LO, PT_SUP_X_LIM_HI] (the limits widened
 *                            by the tolerance)
 *   PT_FAULT_OVERPRESSURE    p_a or p_b above PT_SUP_P_MAX
 *   PT_FAULT_SUPPLY_LOSS     p_s below PT_SUP_SUPPLY_MIN
 * state[PT_SUP_S_FAULT_CHANNEL] then holds the channel the Python message names (PT_CH_*).
 * As in Python, a sample that fails a check before the stale one does not update the value
 * rule's memory.
 *
 * Warnings (pt_sup_check_estimates, after the control step, on theta-hat and p_s), each given
 * once per run and cause, as the Python events:
 *   PT_WARN_REIDENTIFY_SUPPLY  |p_s - p_s,model| > delta held for the hold time
 *   PT_WARN_REIDENTIFY_THETA   a watched theta-hat (M, b_v, A_f) within the band of a bound for
 *                              the hold time; with one PT_WARN_THETA_<name>_<LOW|HIGH> bit per
 *                              Python event (several may come in one sample)
 *
 * A settings vector of another layout (sup[PT_SUP_LAYOUT] != PT_SUP_LAYOUT_ID) makes both checks
 * return PT_STATUS_BAD_LAYOUT and touch nothing.
 *
 * A target and the deploy runtime take the same decisions: both hand this code the same
 * doubles (the 1 ns margin of the time comparisons is inside the packed thresholds). With
 * pt_real double (and without -ffast-math, which would drop the NaN checks) they agree bit for
 * bit. With PT_REAL_FLOAT the thresholds are rounded to float once: decisions on values within
 * a float ulp of a threshold may differ, and times lose resolution on long runs (t as float
 * resolves 1 ms only up to about 2.3 h; keep t running from a recent origin, as the supervisor
 * only takes differences of times).
 *
 * No dynamic memory, no recursion, no global state; only <math.h>, <stddef.h>, <stdint.h>.
 */
#ifndef PT_SUPERVISOR_H
#define PT_SUPERVISOR_H

#include <stdint.h>

#include "ptlaw.h"
#include "pt_sup_layout.h"

#ifdef __cplusplus
extern "C" {
#endif

/* Forget everything seen (Supervisor.reset, the start of a run): every state slot written,
 * the fault channel -1. */
void pt_sup_reset(pt_real *state);

/* 1 when sup has this layout (sup[PT_SUP_LAYOUT] == PT_SUP_LAYOUT_ID), else 0. */
int pt_sup_layout_ok(const pt_real *sup);

/* Supervisor.check_sensors: the sample at time t [s] before the control step. Returns the first
 * fault's bit (PT_FAULT_*), 0 when the sample is fit for the controller, PT_STATUS_BAD_LAYOUT
 * for a settings vector of another layout. sample_times may be NULL (then the value rule). */
uint32_t pt_sup_check_sensors(pt_real *state, const pt_real *sup, pt_real t,
                              const pt_real *sensors, const pt_real *sample_times);

/* Supervisor.check_estimates: after the control step, the measured supply pressure p_s [Pa abs]
 * and theta[6] (theta-hat after the step, e.g. law state + PT_S_THETA). Returns the warnings
 * given in this call (PT_WARN_* bits, details included), 0 for none, PT_STATUS_BAD_LAYOUT for
 * a settings vector of another layout. */
uint32_t pt_sup_check_estimates(pt_real *state, const pt_real *sup, pt_real t, pt_real p_s,
                                const pt_real *theta);

/* The fault of a status word: the index of its lowest fault bit (0 sensor_nan ..
 * PT_FAULT_COUNT - 1), the one Python reports; -1 when no fault bit is set. */
int pt_first_fault(uint32_t status);

/* The Python code of fault index i ("sensor_nan", ...), "" for an index out of range. */
const char *pt_fault_name(int index);

#ifdef __cplusplus
}
#endif

#endif /* PT_SUPERVISOR_H */
