/* LSU GP32 firmware: protocol v2 of docs/GP32_PROTOCOL.md on the MC68HC908GP32.
 *
 * One main loop, no blocking: received bytes are assembled into lines and answered at once;
 * every millisecond of the HAL's tick the sensors are read, motion phases advance and the step
 * line gets its pulses (a Bresenham accumulator spreads `rate` pulses over 1000 ms, so a pulse
 * lands at most 1 ms off its ideal time and the average rate is exact); the laser watchdog
 * counts the milliseconds since the last command line.
 *
 * The behaviour mirrors lsu_driver/emulator.py command for command (the same tests run against
 * both): replies in order, events between them, error codes and texts of the protocol page.
 */
#include <stdint.h>

#include "hal.h"

#define PROTOCOL_VERSION 2
#define MAX_LINE 32u           /* longest command; longer lines get ERR 6 at their newline */
#define RATE_MIN 20
#define RATE_MAX 400
#define WATCHDOG_MAX_MS 60000u
#define DEFAULT_RATE 200u
#define DEFAULT_WATCHDOG_MS 2000u
#define NOMINAL_TRACK 470      /* reported by '?' until homing has measured the track */
#define POS_RATE_MAX 50        /* !POS events per second at most */

enum {
    ERR_UNKNOWN = 1, ERR_ARGUMENT, ERR_NOT_HOMED, ERR_BUSY, ERR_RANGE, ERR_TOO_LONG, ERR_END_SENSOR
};
static const char *const error_text[] = {
    "", "unknown command", "bad argument", "not homed", "busy", "out of range", "line too long",
    "end sensor hit"
};

/* motion phases; homing is SEEK (to the start sensor) -> MEASURE (to the end) -> RETURN */
enum { MO_IDLE, MO_GOTO, MO_MOVE, MO_SEEK, MO_MEASURE, MO_RETURN, MO_SWEEP };

static uint8_t motion;
static int8_t direction;         /* +1 away from the start sensor, -1 towards it */
static uint16_t motion_rate;     /* the rate a motion started with; S changes only later motions */
static uint16_t step_acc;        /* Bresenham accumulator [pulses x 1000 / s] */
static uint8_t motion_fresh;     /* the millisecond the command arrived in is partial: it does not count */
static uint8_t phase_pulses;     /* pulses sent in this phase, saturating: sensors count after a pulse */
static int32_t remaining;        /* pulses left of a G or M */
static int32_t counter;          /* open-loop step counter */
static int32_t track;            /* measured by homing; 0 = not yet */
static uint8_t homed;
static uint16_t rate;
static uint16_t watchdog_ms;
static uint16_t silent_ms;       /* since the last command line, saturating */
static uint8_t laser_on;
static uint8_t sensors;          /* HAL_SENSOR_* seen at the last tick */
static uint32_t now_ms;          /* milliseconds since power-on: the stamp of T, P, !DONE, !POS, !HOME */
static uint16_t pos_period_ms;   /* between !POS events during motion; 0 = off (R0, the power-on value) */
static uint16_t pos_elapsed_ms;  /* since the last !POS; a motion starts with one */
static uint32_t pulse_ms;        /* the last step pulse (or the motion's start): the instant the counter holds since */

static char line[MAX_LINE];
static uint8_t line_len;
static uint8_t line_overflow;

/* ------------------------------------------------------------------------------- output */
static void put_str(const char *s)
{
    while (*s)
        hal_sci_putc((uint8_t)*s++);
}

static void put_uint(uint32_t magnitude)
{
    char digits[10];
    uint8_t n = 0;
    do {
        digits[n++] = (char)('0' + (uint8_t)(magnitude % 10u));
        magnitude /= 10u;
    } while (magnitude);
    while (n)
        hal_sci_putc((uint8_t)digits[--n]);
}

static void put_int(int32_t value)
{
    if (value < 0)
        hal_sci_putc('-');
    put_uint(value < 0 ? (uint32_t)(-value) : (uint32_t)value);
}

/* " <ms>": the instant a reply or event reports, on the millisecond counter */
static void put_stamp_at(uint32_t ms)
{
    hal_sci_putc(' ');
    put_uint(ms);
}

static void put_stamp(void)
{
    put_stamp_at(now_ms);
}

static void put_end(void)
{
    hal_sci_putc('\n');
}

static void reply_ok(void)
{
    put_str("OK");
    put_end();
}

static void reply_err(uint8_t code)
{
    put_str("ERR ");
    hal_sci_putc((uint8_t)('0' + code));
    hal_sci_putc(' ');
    put_str(error_text[code]);
    put_end();
}

static void event_done(void)
{
    put_str("!DONE ");
    put_int(counter);
    put_stamp();
    put_end();
}

/* --------------------------------------------------------------------------------- motion */
static void start_motion(uint8_t kind, int8_t dir)
{
    motion = kind;
    direction = dir;
    motion_rate = rate;
    step_acc = 0;
    motion_fresh = 1;
    phase_pulses = 0;
    pos_elapsed_ms = 0;
    pulse_ms = now_ms;
    hal_step_dir(dir > 0);
}

static void next_phase(uint8_t kind, int8_t dir)
{
    /* the pulse train continues at the same rate: keep the accumulator */
    motion = kind;
    direction = dir;
    phase_pulses = 0;
    hal_step_dir(dir > 0);
}

static void finish_motion(void)
{
    motion = MO_IDLE;
    event_done();
}

/* the sensor in the direction of travel has tripped (only after a pulse of this phase) */
static uint8_t tripped(void)
{
    if (!phase_pulses)
        return 0;
    if (direction < 0)
        return (sensors & HAL_SENSOR_START) != 0;
    return (sensors & HAL_SENSOR_END) != 0;
}

static void motion_tick(void)
{
    if (motion == MO_IDLE)
        return;
    if (motion_fresh) {  /* so a motion of n pulses takes at least n / rate seconds */
        motion_fresh = 0;
        return;
    }
    if (tripped()) {
        switch (motion) {
        case MO_SEEK:
            counter = 0;
            next_phase(MO_MEASURE, +1);
            break;
        case MO_MEASURE:
            track = counter;
            next_phase(MO_RETURN, -1);
            break;
        case MO_RETURN:
            counter = 0;
            homed = 1;
            motion = MO_IDLE;
            put_str("!HOME ");
            put_int(track);
            put_stamp();
            put_end();
            return;
        case MO_SWEEP:
            next_phase(MO_SWEEP, (int8_t)-direction);
            break;
        default:                 /* a G/M ended early: the counter drifted or the target is off-track */
            finish_motion();
            return;
        }
    }
    step_acc += motion_rate;
    if (step_acc < 1000u)
        return;
    step_acc -= 1000u;
    hal_step_pulse();
    counter += direction;
    pulse_ms = now_ms;
    if (phase_pulses != 0xFFu)
        phase_pulses++;
    if ((motion == MO_GOTO || motion == MO_MOVE) && --remaining == 0)
        finish_motion();
}

static void sensor_tick(void)
{
    uint8_t now = hal_sensors();
    uint8_t broken = now & (uint8_t)~sensors;
    sensors = now;
    if (broken & HAL_SENSOR_START) {
        put_str("!END 0");
        put_end();
    }
    if (broken & HAL_SENSOR_END) {
        put_str("!END 1");
        put_end();
    }
}

/* after motion_tick: the counter as it stands, stamped with the instant it got there (its last pulse),
 * not this millisecond: between pulses the carriage is on its way to the next step */
static void position_tick(void)
{
    if (motion == MO_IDLE || !pos_period_ms)
        return;
    if (pos_elapsed_ms == 0) {
        put_str("!POS ");
        put_int(counter);
        put_stamp_at(pulse_ms);
        put_end();
    }
    if (++pos_elapsed_ms >= pos_period_ms)
        pos_elapsed_ms = 0;
}

static void watchdog_tick(void)
{
    if (silent_ms != 0xFFFFu)
        silent_ms++;
    if (laser_on && watchdog_ms && silent_ms > watchdog_ms) {
        laser_on = 0;
        hal_laser(0);
        put_str("!WDOG");
        put_end();
    }
}

/* ------------------------------------------------------------------------------- commands */
/* handlers read their argument from `arg` (HC08: calls through pointers pass no long arguments) */
static int32_t arg;
typedef void (*handler_t)(void);

static void cmd_identify(void)
{
    put_str("OK LSU-GP32 v");
    put_int(PROTOCOL_VERSION);
    put_str(" track=");
    put_int(track ? track : NOMINAL_TRACK);
    put_str(" speed=");
    put_int(rate);
    put_end();
}

static void cmd_status(void)
{
    put_str("OK P");
    put_int(counter);
    put_str(laser_on ? " L1" : " L0");
    put_str(motion != MO_IDLE ? " M1" : " M0");
    put_str(" E");
    hal_sci_putc((sensors & HAL_SENSOR_START) ? '1' : '0');
    hal_sci_putc((sensors & HAL_SENSOR_END) ? '1' : '0');
    put_str(homed ? " H1" : " H0");
    put_str(" T");
    put_uint(now_ms);
    put_end();
}

static void cmd_clock(void)
{
    put_str("OK T");
    put_uint(now_ms);
    put_end();
}

static void cmd_position_rate(void)
{
    uint8_t hz = (uint8_t)arg;
    pos_period_ms = hz ? (uint16_t)(1000u / hz) : 0u;
    pos_elapsed_ms = 0;
    put_str("OK R");
    put_int(hz);
    put_end();
}

static void cmd_laser(void)
{
    uint8_t on = (uint8_t)arg;
    laser_on = (uint8_t)on;
    hal_laser(laser_on);
    put_str(on ? "OK L1" : "OK L0");
    put_end();
}

static void cmd_rate(void)
{
    int32_t steps_per_s = arg;
    rate = (uint16_t)steps_per_s;
    put_str("OK S");
    put_int(steps_per_s);
    put_end();
}

static void cmd_watchdog(void)
{
    int32_t ms = arg;
    watchdog_ms = (uint16_t)ms;
    put_str("OK W");
    put_int(ms);
    put_end();
}

static void cmd_stop(void)
{
    reply_ok();
    finish_motion();
}

static void cmd_goto(void)
{
    int32_t position = arg;
    if (!homed) {
        reply_err(ERR_NOT_HOMED);
        return;
    }
    if (position > track) {
        reply_err(ERR_RANGE);
        return;
    }
    reply_ok();
    if (position == counter) {
        event_done();
        return;
    }
    remaining = position > counter ? position - counter : counter - position;
    start_motion(MO_GOTO, position > counter ? +1 : -1);
}

static void cmd_move(void)
{
    int32_t steps = arg;
    int8_t dir = steps > 0 ? +1 : -1;
    int32_t target = counter + steps;
    if ((dir < 0 && (sensors & HAL_SENSOR_START)) || (dir > 0 && (sensors & HAL_SENSOR_END))) {
        reply_err(ERR_END_SENSOR);
        return;
    }
    if (homed && (target < 0 || target > track)) {
        reply_err(ERR_RANGE);
        return;
    }
    reply_ok();
    remaining = steps > 0 ? steps : -steps;
    start_motion(MO_MOVE, dir);
}

static void cmd_home(void)
{
    reply_ok();
    homed = 0;
    if (sensors & HAL_SENSOR_START) {  /* already on the start sensor: measure straight away */
        counter = 0;
        start_motion(MO_MEASURE, +1);
    } else {
        start_motion(MO_SEEK, -1);
    }
}

static void cmd_sweep(void)
{
    reply_ok();
    start_motion(MO_SWEEP, (sensors & HAL_SENSOR_END) ? -1 : +1);
}

enum { ARG_NONE, ARG_BIT, ARG_INT };
#define BUSY_OK 1u   /* may run while the carriage moves */

/* The command table: letter, argument form, argument limits (ERR 2 outside, except G's lower
 * limit: ERR 5), handler. A new protocol version adds rows here. */
struct command {
    char letter;
    uint8_t arg;
    uint8_t flags;
    int32_t min;
    int32_t max;
    handler_t run;
};

static const struct command commands[] = {
    {'?', ARG_NONE, BUSY_OK, 0, 0, cmd_identify},
    {'P', ARG_NONE, BUSY_OK, 0, 0, cmd_status},
    {'L', ARG_BIT, BUSY_OK, 0, 1, cmd_laser},
    {'S', ARG_INT, BUSY_OK, RATE_MIN, RATE_MAX, cmd_rate},
    {'W', ARG_INT, BUSY_OK, 0, WATCHDOG_MAX_MS, cmd_watchdog},
    {'X', ARG_NONE, BUSY_OK, 0, 0, cmd_stop},
    {'G', ARG_INT, 0, 0, 999999L, cmd_goto},
    {'M', ARG_INT, 0, -999999L, 999999L, cmd_move},
    {'H', ARG_NONE, 0, 0, 0, cmd_home},
    {'C', ARG_NONE, 0, 0, 0, cmd_sweep},
    {'T', ARG_NONE, BUSY_OK, 0, 0, cmd_clock},                       /* v2 */
    {'R', ARG_INT, BUSY_OK, 0, POS_RATE_MAX, cmd_position_rate},     /* v2 */
};
#define N_COMMANDS (sizeof(commands) / sizeof(commands[0]))

static uint8_t is_space(char c)
{
    return c == ' ' || c == '\t' || c == '\v' || c == '\f';
}

/* `[+-]?[0-9]{1,6}` exactly, else 0 */
static uint8_t parse_int(const char *s, uint8_t n, int32_t *out)
{
    uint8_t i = 0, digits = 0;
    uint8_t negative = 0;
    int32_t value = 0;
    if (n && (s[0] == '+' || s[0] == '-')) {
        negative = s[0] == '-';
        i = 1;
    }
    for (; i < n; i++) {
        if (s[i] < '0' || s[i] > '9' || ++digits > 6)
            return 0;
        value = value * 10 + (s[i] - '0');
    }
    if (!digits)
        return 0;
    *out = negative ? -value : value;
    return 1;
}

static void execute(void)
{
    uint8_t start = 0, end = line_len, i;
    const struct command *cmd = 0;
    arg = 0;
    for (i = 0; i < line_len; i++) {
        if ((uint8_t)line[i] >= 0x80u) {
            reply_err(ERR_UNKNOWN);
            return;
        }
        if (line[i] >= 'a' && line[i] <= 'z')
            line[i] = (char)(line[i] - 'a' + 'A');
    }
    while (start < end && is_space(line[start]))
        start++;
    while (end > start && is_space(line[end - 1]))
        end--;
    for (i = 0; start < end && i < N_COMMANDS; i++) {
        if (commands[i].letter == line[start]) {
            cmd = &commands[i];
            break;
        }
    }
    if (!cmd) {
        reply_err(ERR_UNKNOWN);
        return;
    }
    start++;
    if (cmd->arg == ARG_NONE) {
        if (start != end) {  /* "PX" is no command, not a bad argument */
            reply_err(ERR_UNKNOWN);
            return;
        }
    } else if (cmd->arg == ARG_BIT) {
        if (end - start != 1 || (line[start] != '0' && line[start] != '1')) {
            reply_err(ERR_ARGUMENT);
            return;
        }
        arg = line[start] - '0';
    } else {
        if (!parse_int(line + start, (uint8_t)(end - start), &arg)) {
            reply_err(ERR_ARGUMENT);
            return;
        }
        if (arg < cmd->min || arg > cmd->max || (cmd->letter == 'M' && arg == 0)) {
            reply_err(cmd->letter == 'G' ? ERR_RANGE : ERR_ARGUMENT);
            return;
        }
    }
    if (!(cmd->flags & BUSY_OK) && motion != MO_IDLE) {
        reply_err(ERR_BUSY);
        return;
    }
    cmd->run();
}

static void receive(uint8_t c)
{
    if (c == '\r')
        return;
    if (c != '\n') {
        if (line_len < MAX_LINE)
            line[line_len++] = (char)c;
        else
            line_overflow = 1;
        return;
    }
    if (line_len == 0 && !line_overflow)
        return;  /* empty line: no command, no reply */
    silent_ms = 0;
    if (line_overflow)
        reply_err(ERR_TOO_LONG);
    else
        execute();
    line_len = 0;
    line_overflow = 0;
}

/* ------------------------------------------------------------------------------------ main */
/* Called by SDCC's start-up code before the initialised variables are copied (A = 0: copy them).
 * SDCC's HC08 start-up does not clear RAM, and C's zero-initialised statics would otherwise start
 * with whatever the RAM held at power-on: clear 0x40-0x22f, leaving the top of the stack (our own
 * return address) alone. Assembly, because C locals of this port live in the RAM being cleared. */
unsigned char _sdcc_external_startup(void) __naked
{
    __asm
        ldhx    #0x0040
    00001$:
        clr     ,x
        aix     #1
        cphx    #0x0230
        bne     00001$
        clra
        rts
    __endasm;
}

void main(void)
{
    uint16_t last_ms;
    int16_t c;

    hal_init();
    rate = DEFAULT_RATE;
    watchdog_ms = DEFAULT_WATCHDOG_MS;
    sensors = hal_sensors();  /* beams already broken at power-on are no events */
    put_str("!BOOT LSU-GP32 v");
    put_int(PROTOCOL_VERSION);
    put_end();
    last_ms = hal_ms();
    for (;;) {
        hal_service();
        while ((c = hal_sci_getc()) >= 0)
            receive((uint8_t)c);
        while (last_ms != hal_ms()) {
            last_ms++;
            now_ms++;
            sensor_tick();
            motion_tick();
            position_tick();
            watchdog_tick();
        }
    }
}
