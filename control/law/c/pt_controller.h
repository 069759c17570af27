/* pt_controller.h: what a target (PLC, microcontroller) calls every Ts from its timer
 * interrupt: the control law (ptlaw.h) behind the safety supervisor (pt_supervisor.h), with the
 * per-sample order and the fail-safe of pneutune's deploy runtime (control/rig/runtime.py,
 * run_loop):
 *
 *   1. the target reads the sensors (and, if it knows them, each channel's refresh time);
 *   2. the supervisor checks the sample (pt_sup_check_sensors); on the first sample also
 *      |x - x_r| <= sup[PT_SUP_START_TOL] (the runtime's start_position); then that t and the
 *      reference are finite (reference_nan, a check the Python runtime does not need);
 *   3. on a fault: duties = cfg->fail_safe in this very sample, the fault latched: every later
 *      call writes the fail-safe and returns the latched status, until pt_controller_init.
 *      The faulty sample never reaches the law (NaN never does);
 *   4. otherwise the law's step (pt_step_into) on [t, x, p_a, p_b, p_s, x_r, v_r, a_r];
 *   5. the re-identification warnings on theta-hat and p_s (pt_sup_check_estimates);
 *   6. the target writes duties[0..3] (a_in, a_out, b_in, b_out) to the valves.
 *
 * Law state: without `first` (NULL) it is initialised inside the first step, once the sample
 * passed the checks, at x_r of that step's reference and the sample's chamber pressures: the
 * runtime's init_state(x_r(0), p_a(0), p_b(0)), so that a C target reproduces a deploy run
 * sample for sample. With `first` (the reading of sample 0, which the first step then gets
 * again) it is initialised at once at first->x, first->p_a, first->p_b, as the runtime's homing
 * move does (its reference starts at the first reading).
 *
 * Status word (uint32_t, bits in pt_sup_layout.h): the return value of a step holds the latched
 * fault (at most one PT_FAULT_* bit: the first fault, the one the Python runtime reports,
 * pt_first_fault), the config bits (PT_STATUS_BAD_LAYOUT: cfg->law or cfg->sup of another
 * layout; PT_STATUS_BAD_FAIL_SAFE: a fail-safe duty not in [0, 1]; then every valve is closed,
 * the de-energised state, instead of the fail-safe) and the warnings given in this call
 * (PT_WARN_*: the Python events, each once per run and cause). c->status keeps all of them
 * since pt_controller_init, warnings included.
 *
 * Times: t is the rig's time of the sample [s] (the runtime's k Ts), given to both the law and
 * the supervisor; sample times must be on the same clock.
 *
 * pt_real is double unless PT_REAL_FLOAT (ptlaw.h). No dynamic memory, no recursion, no global
 * state; only <math.h>, <stddef.h>, <stdint.h>. A step costs one law step plus a few dozen
 * comparisons.
 *
 * Example (a 4 ms timer interrupt):
 *
 *   static pt_controller_t ctl;            // pt_controller_init(&ctl, &PT_CONFIG, NULL) at boot
 *   void on_timer(void) {
 *       pt_sensors_t s = read_sensors();
 *       pt_reference_t r = reference_at(k);
 *       pt_real d[4];
 *       uint32_t st = pt_controller_step(&ctl, &PT_CONFIG, &s, &r, k * TS, d);
 *       write_valves(d);                   // the fail-safe after a fault
 *       if (st & PT_FAULT_MASK) { report(pt_fault_name(pt_first_fault(st))); }
 *       ++k;
 *   }
 */
#ifndef PT_CONTROLLER_H
#define PT_CONTROLLER_H

#include <stdint.h>

#include "ptlaw.h"
#include "pt_supervisor.h"

#ifdef __cplusplus
extern "C" {
#endif

/* The deployed configuration (read only; typically a const generated from controller.yaml). */
typedef struct {
    pt_real law[PT_CFG_SIZE];   /* pneutune.control.law.layout.pack(controller) */
    pt_real sup[PT_SUP_SIZE];   /* pneutune.control.rig.supervisor_pack.pack_supervisor(...) */
    pt_real fail_safe[4];       /* duties written on a fault, a_in a_out b_in b_out, in [0, 1] */
    const char *sha256;         /* the controller file's sha256 (for the target's log) */
    const char *provenance;     /* where the config came from (for the target's log) */
} pt_config_t;

/* The controller's memory, owned by the caller (a static, not on an interrupt's stack). */
typedef struct {
    pt_real law[PT_STATE_SIZE];      /* the law's state (PT_S_* of pt_layout.h) */
    pt_real sup[PT_SUP_STATE_SIZE];  /* the supervisor's state (PT_SUP_S_*) */
    uint32_t status;                 /* everything raised since pt_controller_init */
} pt_controller_t;

/* One sample's readings: position [m], chamber and supply pressures [Pa abs]. */
typedef struct {
    pt_real x, p_a, p_b, p_s;
} pt_sensors_t;

/* The reference at the sample: position [m], velocity [m/s], acceleration [m/s^2]. */
typedef struct {
    pt_real x_r, v_r, a_r;
} pt_reference_t;

/* Start (or restart) a run: checks cfg, resets the supervisor and the latched status, and
 * initialises the law state from `first` (or, NULL, in the first step; see above). Returns 0,
 * or 1 when cfg is unusable (c->status has PT_STATUS_BAD_LAYOUT or PT_STATUS_BAD_FAIL_SAFE and
 * every step closes every valve). A non-finite `first` is not used (the first step's
 * supervisor check faults on it anyway). */
int pt_controller_init(pt_controller_t *c, const pt_config_t *cfg, const pt_sensors_t *first);

/* One sample at time t [s]: writes duties[0..3], returns the status (see above). The value
 * rule judges staleness (pressure channels repeating bit for bit). */
uint32_t pt_controller_step(pt_controller_t *c, const pt_config_t *cfg, const pt_sensors_t *s,
                            const pt_reference_t *r, pt_real t, pt_real duties[4]);

/* The same, with the time each channel (x, p_a, p_b, p_s) was last refreshed [s], on the clock
 * of t, for targets that know it (the rule of rigs with sample_times()); NULL: the value rule. */
uint32_t pt_controller_step_stamped(pt_controller_t *c, const pt_config_t *cfg,
                                    const pt_sensors_t *s, const pt_real *sample_times,
                                    const pt_reference_t *r, pt_real t, pt_real duties[4]);

/* A fault the target found itself (PT_FAULT_RIG_IO: a failed read or write; a watchdog):
 * latches the lowest PT_FAULT_* bit of `fault` (PT_FAULT_RIG_IO when it has none) unless a
 * fault is latched already, writes the fail-safe duties and returns the latched status. */
uint32_t pt_controller_trip(pt_controller_t *c, const pt_config_t *cfg, uint32_t fault,
                            pt_real duties[4]);

#ifdef __cplusplus
}
#endif

#endif /* PT_CONTROLLER_H */
