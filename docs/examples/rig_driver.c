/* rig_driver.c: a complete rig driver speaking pneutune.rig/1 on stdin/stdout (docs/deploy.md).
 *
 *   gcc -std=c99 -O2 -Wall -o rig_driver rig_driver.c -lm
 *   python -m pneutune.control.driver check ./rig_driver
 *   deploy data/controller-paper.yaml --rig exec:./rig_driver --duration 2
 *   record --experiment identification --sample-period 0.0005 \
 *          --rig exec:"./rig_driver --sample-period {sample_period}" --out run.mcap
 *
 * Its rig is a toy, not a cylinder: each chamber pressure relaxes toward the supply through its
 * inlet valve and toward ambient through its outlet, at a rate proportional to the duty, and is
 * compressed or expanded by the piston; the piston moves at the speed that the net force, less
 * a Coulomb friction, drives through viscous friction, stopping at the stroke ends. It exists
 * to show the protocol. A real driver replaces step() and the sensor
 * values with its hardware: R reads the channels, W sets the PWM duties, A waits for the tick.
 *
 * --sample-period S makes it sample (and tick) every S seconds, faster than the control
 * period rig.Ts = 4 ms that its rig block keeps, as a data-acquisition card does; S must
 * divide rig.Ts.
 */
#define _POSIX_C_SOURCE 200809L /* signal(SIGPIPE, ...) */
#include <math.h>
#include <signal.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#if __BYTE_ORDER__ != __ORDER_LITTLE_ENDIAN__
#error "pneutune.rig/1 is little-endian: swap the bytes of every number on this machine"
#endif

#define RIG_TS 0.004     /* control period of the rig block [s] */
#define P0 101325.0      /* ambient [Pa abs] */
#define P_S 6.0e5        /* supply [Pa abs] */
#define A_A 7.854e-3     /* piston area, chamber A [m^2] */
#define A_B 7.54e-3      /* annulus area, chamber B [m^2] */
#define X_MIN -0.0015    /* stroke [m] */
#define X_MAX 0.0485
#define V0_A 5.036e-5    /* dead volumes [m^3] */
#define V0_B 2.916e-5
#define N_POLY 1.2       /* polytropic exponent */
#define RATE 30.0        /* pressure relaxation rate at full duty [1/s] */
#define B_V 20000.0      /* viscous friction [N s/m] */
#define F_C 40.0         /* Coulomb friction [N] */

static const char HELLO[] = /* %.17g: the sample period Ts */
    "{\"protocol\": \"pneutune.rig/1\", \"Ts\": %.17g, \"rig\": {"
    "\"A_a\": 7.854e-3, \"A_b\": 7.54e-3, \"x_min\": -0.0015, \"x_max\": 0.0485, "
    "\"V0a\": 5.036e-5, \"V0b\": 2.916e-5, \"p0\": 101325.0, \"p_s\": 6.0e5, "
    "\"T0\": 283.15, \"n\": 1.2, \"R\": 287.0, \"Ts\": 0.004, \"pwm_hz\": 60.0, "
    "\"pwm_update\": \"immediate\"}}";

static double ts = RIG_TS;                           /* sample period [s] */
static long k;                                       /* sample index: t = k Ts */
static double x = 0.0235, p_a = P0, p_b = P0;        /* at rest at mid-stroke */
static double duty[4];                               /* a_in, a_out, b_in, b_out */

static void fail_safe(void) { memset(duty, 0, sizeof duty); } /* hardware: all coils off */

static void gone(void) { fail_safe(); exit(1); }     /* a failed write: the client is gone */

static void put(const void *data, size_t n) {
    if (n > 0 && fwrite(data, 1, n, stdout) != n) gone();
}

static void flush(void) {
    if (fflush(stdout) != 0) gone();
}

static void reply_ok(const void *body, size_t n) {
    put("K", 1);
    put(body, n);
    flush();
}

static int reply_error(const char *message) {          /* close the valves, E, exit 1 */
    uint32_t n = (uint32_t)strlen(message);
    fail_safe();
    put("E", 1);
    put(&n, sizeof n);
    put(message, n);
    flush();
    return 1;
}

static void step(void) {                              /* the toy rig over one sample */
    const double h = ts / 8.0;
    for (int i = 0; i < 8; i++) {
        double f = p_a * A_A - p_b * A_B - P0 * (A_A - A_B);  /* net pressure force [N] */
        double v = fabs(f) <= F_C ? 0.0 : (f - copysign(F_C, f)) / B_V;
        double v_a = V0_A + A_A * (x - X_MIN), v_b = V0_B + A_B * (X_MAX - x);
        if ((x <= X_MIN && v < 0.0) || (x >= X_MAX && v > 0.0))
            v = 0.0;                                          /* on an end stop */
        p_a += h * (RATE * (duty[0] * (P_S - p_a) - duty[1] * (p_a - P0))
                    - N_POLY * p_a * A_A * v / v_a);
        p_b += h * (RATE * (duty[2] * (P_S - p_b) - duty[3] * (p_b - P0))
                    + N_POLY * p_b * A_B * v / v_b);
        x = fmin(fmax(x + h * v, X_MIN), X_MAX);
    }
}

int main(int argc, char **argv) {
    int op;
    char hello[sizeof HELLO + 32];
    if (argc == 3 && strcmp(argv[1], "--sample-period") == 0) {
        char *end;
        double n;
        ts = strtod(argv[2], &end);
        n = RIG_TS / ts;                                  /* whole samples per rig.Ts */
        if (*end != '\0' || !(ts > 0.0) || fabs(n - floor(n + 0.5)) > 1e-9 * n) {
            fprintf(stderr, "error: --sample-period must divide rig.Ts = %g s\n", RIG_TS);
            return 2;
        }
    } else if (argc != 1) {
        fprintf(stderr, "usage: %s [--sample-period S]\n", argv[0]);
        return 2;
    }
    snprintf(hello, sizeof hello, HELLO, ts);
    signal(SIGPIPE, SIG_IGN);        /* a vanished client is a write error (put), not a kill */
    while ((op = getchar()) != EOF) {
        if (op == 'H') {
            uint32_t n = (uint32_t)strlen(hello);
            put("K", 1);
            put(&n, sizeof n);
            put(hello, n);
            flush();
        } else if (op == 'R') {
            double t = k * ts, r[9] = {t, x, p_a, p_b, P_S, t, t, t, t};
            reply_ok(r, sizeof r);
        } else if (op == 'W') {
            double d[4];
            if (fread(d, sizeof d, 1, stdin) != 1) break;  /* end of input */
            for (int i = 0; i < 4; i++)
                if (!(d[i] >= 0.0 && d[i] <= 1.0))          /* NaN fails this too */
                    return reply_error("duties must be in [0, 1]");
            memcpy(duty, d, sizeof d);
            reply_ok("", 0);
        } else if (op == 'A') {
            step();
            k++;
            double t = k * ts;
            reply_ok(&t, sizeof t);
        } else if (op == 'C') {
            fail_safe();
            reply_ok("", 0);
            return 0;
        } else {
            return reply_error("unknown request");
        }
    }
    fail_safe();                                        /* the client is gone */
    return 0;
}
