/* main.c: a bare-metal control loop around the emitted controller (deploy --emit c), worked
 * through with stub I/O (stub_io.h) so that it builds and runs on a host:
 *
 *     deploy data/controller-paper.yaml --emit c --out build/axis1
 *     make -C build/axis1                       (libptcontroller.a; or cc -std=c99 -O2 -c *.c)
 *     cc -std=c99 -O2 -I build/axis1 -o demo docs/examples/baremetal/main.c
 *        docs/examples/baremetal/stub_io.c build/axis1/libptcontroller.a -lm
 *     ./demo                                    (exit 0: the run ended without a fault)
 *
 * The loop is the one of a microcontroller without an operating system: wait for the 4 ms
 * tick, read the sensors, compute the reference, step the controller, write the duties, kick
 * the watchdog, then act on the status word. Everything the controller needs is static; no
 * heap. On a target the stubs are the board's drivers and printf is the target's log (UART,
 * fieldbus); the loop itself does not change.
 */
#include <math.h>
#include <stdint.h>
#include <stdio.h>

#include "pt_config.h"
#include "stub_io.h"

/* The reference: a 0.5 Hz sine about mid-stroke over half the stroke (the paper's test). */
#define REF_HZ 0.5

/* The controller's memory: static, never on the stack of an interrupt. */
static pt_controller_t ctl;

static void reference_at(const pt_config_t *cfg, pt_real t, pt_reference_t *r)
{
    double x_min = (double)cfg->law[PT_CFG_X_MIN];
    double x_max = (double)cfg->law[PT_CFG_X_MAX];
    double centre = 0.5 * (x_min + x_max);
    double amp = 0.25 * (x_max - x_min);
    double w = 2.0 * 3.141592653589793 * REF_HZ;
    double tt = (double)t;
    r->x_r = (pt_real)(centre + amp * sin(w * tt));
    r->v_r = (pt_real)(amp * w * cos(w * tt));
    r->a_r = (pt_real)(-amp * w * w * sin(w * tt));
}

int main(void)
{
    const pt_config_t *cfg = &PT_CONFIG;
    const pt_real ts = cfg->law[PT_CFG_TS];
    pt_real duties[4];
    pt_sensors_t s;
    pt_reference_t r;
    uint32_t k = 0u;
    uint32_t st = 0u;
    uint32_t warned = 0u;
    int fault = -1;

    printf("controller sha256 %s\n  %s\n", cfg->sha256, cfg->provenance);
    stub_io_init(cfg);
    /* boot: check the config, reset the supervisor; the law state starts at the first sample */
    if (pt_controller_init(&ctl, cfg, NULL) != 0) {
        (void)pt_controller_trip(&ctl, cfg, PT_FAULT_RIG_IO, duties); /* every valve closed */
        (void)stub_write_valves(duties);
        printf("unusable config (status 0x%08lx): valves closed\n", (unsigned long)ctl.status);
        return 2;
    }

    while (stub_wait_tick()) {
        /* t from the start of the run (k Ts): the supervisor only takes differences of times */
        pt_real t = (pt_real)k * ts;
        reference_at(cfg, t, &r);
        if (stub_read_sensors(&r, &s) != 0) {
            st = pt_controller_trip(&ctl, cfg, PT_FAULT_RIG_IO, duties);
        } else {
            st = pt_controller_step(&ctl, cfg, &s, &r, t, duties);
        }
        /* the duties first: after a fault they are the fail-safe, written in this very tick */
        if (stub_write_valves(duties) != 0) {
            st = pt_controller_trip(&ctl, cfg, PT_FAULT_RIG_IO, duties);
            (void)stub_write_valves(duties);
        }
        stub_watchdog_kick();

        /* then the status word: the latched fault, the warnings given in this call */
        if ((st & PT_WARN_MASK) != 0u) {
            warned |= st & PT_WARN_MASK;
            printf("t = %.3f s: warning%s%s: run identify again\n", (double)t,
                   (st & PT_WARN_REIDENTIFY_SUPPLY) != 0u ? " reidentify_supply" : "",
                   (st & PT_WARN_REIDENTIFY_THETA) != 0u ? " reidentify_theta" : "");
        }
        if ((st & PT_FAULT_MASK) != 0u) {
            fault = pt_first_fault(st);
            printf("t = %.3f s: fault %s: valves in the fail-safe state\n", (double)t,
                   pt_fault_name(fault));
            /* a target stays in the loop writing the fail-safe (every later step returns it)
             * until an operator restarts the run with pt_controller_init; the host run ends */
            break;
        }
        ++k;
    }

    printf("%lu ticks of %.1f ms, %lu watchdog kicks, mean duty %.4f, theta-hat M %.4f kg, "
           "status 0x%08lx%s\n", (unsigned long)stub_ticks(), 1.0e3 * (double)ts,
           (unsigned long)stub_kicks(), stub_duty_sum() / (4.0 * (double)stub_ticks()),
           (double)ctl.law[PT_S_THETA], (unsigned long)ctl.status,
           warned != 0u ? " (warnings given)" : "");
    return fault < 0 ? 0 : 1;
}
