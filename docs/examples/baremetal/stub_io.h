/* stub_io.h: stand-ins for a target's I/O in the bare-metal example (main.c).
 *
 * On a target these are the board's drivers: a 4 ms hardware timer, the ADC channels of the
 * position and pressure transmitters, the PWM outputs of the four solenoid valves and the
 * watchdog. Here they run on a host: the "timer" returns at once for STUB_TICKS ticks, the
 * "sensors" read a piston that follows the reference within a few tens of micrometres with
 * noisy pressures around mid-supply (no plant: enough for the supervisor to see a working rig),
 * and the "valves" remember the last duties written.
 */
#ifndef STUB_IO_H
#define STUB_IO_H

#include <stdint.h>

#include "pt_controller.h"

#ifndef STUB_TICKS
#define STUB_TICKS 2500u /* 10 s at 4 ms */
#endif

/* Set the stubs up for a controller (its stroke, ambient and supply pressures). */
void stub_io_init(const pt_config_t *cfg);

/* Wait for the next timer tick: 1, or 0 once the host run is over (a target never returns 0). */
int stub_wait_tick(void);

/* Read the four sensors for the sample whose reference is r: 0, or nonzero for a failed read
 * (an ADC timeout, a CRC error on a fieldbus). */
int stub_read_sensors(const pt_reference_t *r, pt_sensors_t *s);

/* Write the duties of a_in, a_out, b_in, b_out to the PWM outputs: 0, or nonzero on failure. */
int stub_write_valves(const pt_real duties[4]);

/* Kick the hardware watchdog (on a target: it cuts the valve coils' power if not kicked). */
void stub_watchdog_kick(void);

/* What the stubs saw: ticks, watchdog kicks, the sum of every duty written (for the summary). */
uint32_t stub_ticks(void);
uint32_t stub_kicks(void);
double stub_duty_sum(void);

#endif /* STUB_IO_H */
