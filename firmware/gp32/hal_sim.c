/* HAL for the ucsim HC08 simulator (shc08), which models the CPU but no SCI, timer or ports.
 *
 * All I/O goes through ucsim's simulator interface, a mailbox byte at SIF_ADDRESS (an address
 * no GP32 peripheral or memory uses), whose input and output files the host-side board
 * (lsu_driver/firmware.py) holds. One byte stream each way carries everything, in order, so no
 * pin edge or tick is ever lost or reordered against the serial bytes:
 *
 *   board -> firmware   0x00-0x7F  a received SCI byte
 *                       0x80+n     n milliseconds passed (n = 1..63)
 *                       0xC0+s     the sensor pins: s = HAL_SENSOR_* bits (sent first, and as
 *                                  the answer to a step pulse)
 *                       0xC4, b    a received SCI byte b | 0x80 (8-bit transparency)
 *                       0xC5, n    before a sensor answer: the next n pulses (0..127) cannot
 *                                  change the sensors (the carriage is that far from both ends),
 *                                  so they need no answer
 *   firmware -> board   0x00-0x7F  a sent SCI byte
 *                       0x80+p     pins changed: p = step | dir << 1 | laser << 2; a rising step
 *                                  edge is followed by the millisecond it belongs to (14 bits, low 7
 *                                  first), then the firmware waits for the board's sensor answer
 *
 * Waiting for the sensors after a pulse is what the real firmware gets for free (the beam breaks
 * while the pulse moves the carriage): a sensor trips before the next pulse, however far the
 * simulation lags. The board's pulse credit keeps that wait to the few pulses near the ends: a
 * round trip per pulse would slow the simulation below real time on a loaded host. The firmware's time is the board's wall clock (ticks), not the simulated
 * cycles. ucsim's read does not block (it answers 0 when nothing is waiting), so the HAL asks
 * first whether input is there: a running simulator spins one host core.
 */
#include "hal.h"

#define SIF_ADDRESS 0x7fff
#define SIF (*(volatile uint8_t *)SIF_ADDRESS)
#define SIF_READ 'r'
#define SIF_WRITE 'w'
#define SIF_INPUT_WAITING 'f'

#define IN_TICK 0x80u
#define IN_SENSORS 0xC0u
#define IN_HIGH_BYTE 0xC4u
#define IN_CREDIT 0xC5u
#define OUT_PINS 0x80u

#define PIN_STEP 0x01u
#define PIN_DIR 0x02u
#define PIN_LASER 0x04u

#define RX_SIZE 48u   /* SCI bytes that arrive while a pulse waits for its sensor answer */

static uint16_t ms;
static uint8_t ms_pending;    /* received, not yet handed out: hal_service releases one per turn */
static uint8_t sensor_bits;
static uint8_t rx_buf[RX_SIZE];
static uint8_t rx_head, rx_tail;
static uint8_t pins;
static uint8_t credit;        /* pulses the board lets pass without a sensor answer */

static uint8_t sif_read(void)
{
    do {
        SIF = SIF_INPUT_WAITING;
    } while (!SIF);
    SIF = SIF_READ;
    return SIF;
}

static void sif_write(uint8_t c)
{
    SIF = SIF_WRITE;
    SIF = c;
}

static void set_pins(uint8_t value)
{
    pins = value;
    sif_write(OUT_PINS | pins);
}

static void rx_put(uint8_t c)
{
    uint8_t next = (uint8_t)((rx_head + 1u) % RX_SIZE);
    if (next != rx_tail) {  /* full: the byte is lost, as in an overrun of the real SCI */
        rx_buf[rx_head] = c;
        rx_head = next;
    }
}

/* one input item; returns 1 when it was the sensor pins */
static uint8_t take_input(void)
{
    uint8_t c = sif_read();
    if (c < 0x80u) {
        rx_put(c);
    } else if (c < IN_SENSORS) {
        ms_pending += c & 0x3Fu;  /* the board sends at most 63 ms ahead of the firmware */
    } else if (c == IN_HIGH_BYTE) {
        rx_put(sif_read() | 0x80u);
    } else if (c == IN_CREDIT) {
        credit = sif_read();
    } else {
        sensor_bits = c & 0x03u;
        return 1;
    }
    return 0;
}

void hal_init(void)
{
    while (!take_input())  /* the board announces the sensor pins first */
        ;
    set_pins(0);
}

/* One millisecond per main-loop turn, so a pulse's millisecond stamp is the one the firmware is
 * working on, even when the simulation lags behind the board's clock; the next input is taken
 * only after the milliseconds that passed before it (the stream's order is the order of events). */
void hal_service(void)
{
    if (!ms_pending) {
        take_input();
        return;
    }
    ms++;
    ms_pending--;
}

uint16_t hal_ms(void)
{
    return ms;
}

int16_t hal_sci_getc(void)
{
    uint8_t c;
    if (rx_tail == rx_head)
        return -1;
    c = rx_buf[rx_tail];
    rx_tail = (uint8_t)((rx_tail + 1u) % RX_SIZE);
    return c;
}

void hal_sci_putc(uint8_t c)
{
    sif_write(c & 0x7Fu);
}

void hal_step_dir(uint8_t forward)
{
    set_pins(forward ? (pins | PIN_DIR) : (pins & (uint8_t)~PIN_DIR));
}

void hal_step_pulse(void)
{
    set_pins(pins | PIN_STEP);
    sif_write((uint8_t)(ms & 0x7Fu));
    sif_write((uint8_t)((ms >> 7) & 0x7Fu));
    set_pins(pins & (uint8_t)~PIN_STEP);
    if (credit) {
        credit--;
        return;
    }
    while (!take_input())
        ;
}

void hal_laser(uint8_t on)
{
    set_pins(on ? (pins | PIN_LASER) : (pins & (uint8_t)~PIN_LASER));
}

uint8_t hal_sensors(void)
{
    return sensor_bits;
}
