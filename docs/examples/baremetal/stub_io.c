/* stub_io.c: the host stand-ins of stub_io.h (no plant, no hardware; see stub_io.h). */
#include <math.h>
#include <stdint.h>

#include "stub_io.h"

static uint32_t ticks;
static uint32_t kicks;
static double duty_sum;
static uint32_t noise_state = 2463534242u;
static double p0, p_s, p_mid, x_lo, x_hi, ts;

/* A uniform number in [-1, 1) (xorshift32): the sensors' noise. */
static double noise(void)
{
    noise_state ^= noise_state << 13;
    noise_state ^= noise_state >> 17;
    noise_state ^= noise_state << 5;
    return (double)noise_state / 2147483648.0 - 1.0;
}

void stub_io_init(const pt_config_t *cfg)
{
    ticks = 0u;
    kicks = 0u;
    duty_sum = 0.0;
    p0 = (double)cfg->law[PT_CFG_P0];
    p_s = (double)cfg->sup[PT_SUP_P_S_MODEL];
    p_mid = 0.5 * (p0 + p_s);
    x_lo = (double)cfg->sup[PT_SUP_X_LIM_LO];
    x_hi = (double)cfg->sup[PT_SUP_X_LIM_HI];
    ts = (double)cfg->law[PT_CFG_TS];
}

int stub_wait_tick(void)
{
    /* a target: wait for the timer's flag (or sleep until its interrupt), then clear it */
    if (ticks >= STUB_TICKS) {
        return 0;
    }
    ++ticks;
    return 1;
}

int stub_read_sensors(const pt_reference_t *r, pt_sensors_t *s)
{
    double x = (double)r->x_r + 20.0e-6 * noise();
    double swing = 0.2 * (p_s - p0) * sin(2.0 * 3.141592653589793 * 0.5 * ts * ticks);
    if (x < x_lo) {
        x = x_lo;
    }
    if (x > x_hi) {
        x = x_hi;
    }
    s->x = (pt_real)x;
    s->p_a = (pt_real)(p_mid + swing + 300.0 * noise());
    s->p_b = (pt_real)(p_mid - swing + 300.0 * noise());
    s->p_s = (pt_real)(p_s + 300.0 * noise());
    return 0;
}

int stub_write_valves(const pt_real duties[4])
{
    int i;
    for (i = 0; i < 4; ++i) {
        if (!(duties[i] >= 0.0f && duties[i] <= 1.0f)) {
            return 1; /* a PWM driver refuses what it cannot output */
        }
        duty_sum += (double)duties[i];
    }
    return 0;
}

void stub_watchdog_kick(void)
{
    ++kicks;
}

uint32_t stub_ticks(void)
{
    return ticks;
}

uint32_t stub_kicks(void)
{
    return kicks;
}

double stub_duty_sum(void)
{
    return duty_sum;
}
