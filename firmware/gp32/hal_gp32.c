/* HAL of the real board: MC68HC908GP32 registers per its data sheet (MC68HC908GP32/H rev. 6).
 *
 * Clock: 32.768 kHz crystal, PLL to a 7.3728 MHz bus (R = 1, N = 225, E = 2, L = 192: the
 * data sheet's PLL programming procedure), so both 9600 and 115200 baud divide exactly.
 * Tick: TIM1 overflow every 1 ms. SCI: 8N1, interrupt-driven ring buffers both ways, so a
 * reply never delays a step pulse. COP watchdog on: a hung main loop resets the chip (after 8 s), and
 * after any reset the ports are inputs, which leaves the laser off.
 */
#include "hal.h"

#include <mc68hc908gp32.h>
/* one-letter bit names of the header that would clash with ordinary identifiers */
#undef M
#undef R
#undef OR
#undef TC
#undef PE
#undef FE
#undef NF

#ifndef LSU_BAUD
#define LSU_BAUD 9600
#endif

/* register bits (data sheet names) */
#define PCTL_PLLON 0x20u
#define PCTL_BCS 0x10u
#define PCTL_VPR_E2 0x02u
#define PBWC_AUTO 0x80u
#define PBWC_LOCK 0x40u
#define T1SC_TOF 0x80u
#define T1SC_TOIE 0x40u
#define T1SC_TSTOP 0x20u
#define T1SC_TRST 0x10u
#define SCC1_ENSCI 0x40u
#define SCC2_SCTIE 0x80u
#define SCC2_SCRIE 0x20u
#define SCC2_TE 0x08u
#define SCC2_RE 0x04u
#define SCS1_SCTE 0x80u
#define SCS1_SCRF 0x20u

#define BUS_HZ 7372800UL
#define TICK_MODULO ((uint16_t)(BUS_HZ / 1000UL - 1UL))   /* TIM1 counts 0..modulo: 1 ms */
#if LSU_BAUD == 115200
#define SCBR_VALUE 0x00u   /* bus / 64 / 1 / 1 */
#elif LSU_BAUD == 9600
#define SCBR_VALUE 0x12u   /* bus / 64 / 3 (SCP = 01) / 4 (SCR = 010) */
#else
#error "LSU_BAUD must be 9600 or 115200"
#endif

/* outputs on port D: PTA0 is the monitor mode's serial line, so the step line stays off it */
#define STEP_BIT 0x01u    /* PTD0 */
#define DIR_BIT 0x02u     /* PTD1 */
#define LASER_BIT 0x04u   /* PTD2 */
#define SENSOR_START_BIT 0x01u  /* PTB0 */
#define SENSOR_END_BIT 0x02u    /* PTB1 */

#define RX_SIZE 48u   /* > 1 command line: a full line can arrive while the main loop replies */
#define TX_SIZE 80u   /* > 1 device line; a longer burst waits for the transmitter */

static volatile uint16_t ms;
static volatile uint8_t rx_buf[RX_SIZE];
static volatile uint8_t rx_head, rx_tail;
static volatile uint8_t tx_buf[TX_SIZE];
static volatile uint8_t tx_head, tx_tail;


void hal_init(void)
{
    CONFIG2 = 0x00;            /* write-once: defaults */
    CONFIG1 = 0x00;            /* write-once: COP on (2^18 - 2^4 crystal cycles: 8 s at 32.768 kHz), LVI on */
    PTD = 0;                   /* step low, laser off before the pins become outputs */
    DDRD = STEP_BIT | DIR_BIT | LASER_BIT;
    DDRB = 0;                  /* sensors are inputs */

    PCTL = 0;                  /* PLL off while it is programmed */
    PMSH = 0x00;
    PMSL = 225u;               /* N */
    PMRS = 192u;               /* L */
    PMDS = 1u;                 /* R */
    PCTL = PCTL_PLLON | PCTL_VPR_E2;
    PBWC = PBWC_AUTO;
    while (!(PBWC & PBWC_LOCK))
        COPCTL = 0;
    PCTL |= PCTL_BCS;          /* bus clock from the PLL */

    T1SC = T1SC_TSTOP | T1SC_TRST;
    T1MOD = TICK_MODULO;
    T1SC = T1SC_TOIE;          /* prescaler 1, running */

    SCC1 = SCC1_ENSCI;         /* 8N1 */
    SCBR = SCBR_VALUE;
    SCC2 = SCC2_TE | SCC2_RE | SCC2_SCRIE;
    __asm__("cli");
}

void hal_service(void)
{
    COPCTL = 0;
}

uint16_t hal_ms(void)
{
    uint16_t now;
    __asm__("sei");            /* a 16-bit read is two bus reads */
    now = ms;
    __asm__("cli");
    return now;
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
    uint8_t next = (uint8_t)((tx_head + 1u) % TX_SIZE);
    while (next == tx_tail)    /* full: the transmit interrupt frees a slot within one byte time */
        COPCTL = 0;
    tx_buf[tx_head] = c;
    tx_head = next;
    SCC2 |= SCC2_SCTIE;
}

void hal_step_dir(uint8_t forward)
{
    if (forward)
        PTD |= DIR_BIT;
    else
        PTD &= (uint8_t)~DIR_BIT;
}

void hal_step_pulse(void)
{
    /* the SAA1027 needs a pulse of a few microseconds: several bus cycles of 136 ns */
    PTD |= STEP_BIT;
    __asm__("nop\n nop\n nop\n nop\n nop\n nop\n nop\n nop");
    PTD &= (uint8_t)~STEP_BIT;
}

void hal_laser(uint8_t on)
{
    if (on)
        PTD |= LASER_BIT;
    else
        PTD &= (uint8_t)~LASER_BIT;
}

uint8_t hal_sensors(void)
{
    uint8_t pins = PTB;
    return (uint8_t)(((pins & SENSOR_START_BIT) ? HAL_SENSOR_START : 0u) |
                     ((pins & SENSOR_END_BIT) ? HAL_SENSOR_END : 0u));
}

/* TIM1 overflow, vector 0xFFF2 */
void hal_tim1_overflow(void) __interrupt(6)
{
    (void)T1SC;                /* TOF clears by reading T1SC with TOF set, then writing 0 to it */
    T1SC &= (uint8_t)~T1SC_TOF;
    ms++;
}

/* SCI receive, vector 0xFFE4 */
void hal_sci_receive(void) __interrupt(13)
{
    uint8_t next;
    (void)SCS1;                /* SCRF clears by reading SCS1, then SCDR */
    next = (uint8_t)((rx_head + 1u) % RX_SIZE);
    if (next != rx_tail) {
        rx_buf[rx_head] = SCDR;
        rx_head = next;
    } else {
        (void)SCDR;            /* overrun: the byte is lost; the line will fail to parse */
    }
}

/* SCI transmit, vector 0xFFE2 */
void hal_sci_transmit(void) __interrupt(14)
{
    if (tx_tail == tx_head) {
        SCC2 &= (uint8_t)~SCC2_SCTIE;
        return;
    }
    (void)SCS1;                /* SCTE clears by reading SCS1, then writing SCDR */
    SCDR = tx_buf[tx_tail];
    tx_tail = (uint8_t)((tx_tail + 1u) % TX_SIZE);
}
