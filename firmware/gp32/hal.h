/* Hardware abstraction of the LSU's GP32 board: everything the firmware touches.
 *
 * Two implementations: hal_gp32.c drives the MC68HC908GP32's SCI, timer and ports (the real unit);
 * hal_sim.c runs under the ucsim HC08 simulator, where a host-side board program supplies the
 * millisecond tick, the received bytes and the sensor pins through the simulator interface.
 *
 * Pins (hal_gp32.c): PTD0 = step pulse, PTD1 = direction (1 = away from the start sensor),
 * PTD2 = laser (1 = on), PTB0 = start sensor, PTB1 = end sensor (1 = beam broken, as the thesis'
 * comparator drives them). PTA0 stays free for the monitor mode's serial line. After a reset every port is an input, so the laser is off until the
 * firmware switches it on.
 */
#ifndef LSU_HAL_H
#define LSU_HAL_H

#include <stdint.h>

#define HAL_SENSOR_START 0x01u
#define HAL_SENSOR_END   0x02u

/* ports, clock, SCI, tick; the laser and the step line are off/low afterwards */
void hal_init(void);
/* called once per main-loop turn: the real board kicks the COP watchdog; the simulator
 * waits here for the next input from the host-side board (tick, byte or sensor change) */
void hal_service(void);
/* free-running millisecond counter (wraps at 65536) */
uint16_t hal_ms(void);
/* next received byte, or -1 when none is waiting */
int16_t hal_sci_getc(void);
/* queue one byte for sending; never blocks longer than one byte time when the queue is full */
void hal_sci_putc(uint8_t c);
/* direction line: 1 = away from the start sensor */
void hal_step_dir(uint8_t forward);
/* one pulse on the step line (high, then low: the SAA1027 steps on the rising edge) */
void hal_step_pulse(void);
void hal_laser(uint8_t on);
/* HAL_SENSOR_START | HAL_SENSOR_END bits of the beams that are broken right now */
uint8_t hal_sensors(void);

#ifdef LSU_HAL_GP32
/* SDCC emits the interrupt vector table in the module that defines main(), so that module must
 * see the interrupt handlers of hal_gp32.c (vector = 0xFFFE - 2 x number) */
void hal_tim1_overflow(void) __interrupt(6);   /* 0xFFF2 */
void hal_sci_receive(void) __interrupt(13);    /* 0xFFE4 */
void hal_sci_transmit(void) __interrupt(14);   /* 0xFFE2 */
#endif

#endif
