/* The rig's I/O daemon (rpr-board): shared declarations of its three modules.
 *
 *   board_io.c    pins: PWM chips by address, GPIO lines (character device or sysfs), the ADC by
 *                 name, all under a root directory ("/" on the board, a fake tree in tests);
 *   board_core.c  the protocol, the state machine and the safety rules (no clock, no socket:
 *                 every entry point takes the monotonic time, so tests can step it);
 *   board_main.c  the command line, the key file, the UDP socket, the periodic loop, signals.
 *
 * The pin map, the safety limits and the PWM period come from board_config.h, generated from
 * hardware/pins.py, hardware/daemon.py (Safety) and hardware/convert.py by hardware/daemon.py.
 */
#ifndef RPR_BOARD_H
#define RPR_BOARD_H
#include <stddef.h>
#include <stdint.h>

#include "board_config.h"
#include "hmac_sha256.h"

#define LEGS 3
#define PATHLEN 512

/* the protocol: magic, version, lengths, types, flags, states, fault bits (generated from
   hardware/protocol.py) */
#include "board_protocol.h"

/* counters, in this order in the status line (names as in hardware/daemon.py COUNTERS) */
enum { C_RECEIVED, C_COMMANDS, C_MALFORMED, C_UNAUTHENTICATED, C_OLD_SESSION, C_OUT_OF_SEQUENCE, C_STALE, C_REFUSED,
       C_SESSIONS, C_FAULTS, C_TICKS, C_WRITES, C_THROTTLED, C_COUNT };
extern const char *const COUNTER_NAMES[C_COUNT];

typedef struct {
    double v_max, slew, watchdog_s, stale_ms, adc_stale_s, travel_lo, travel_hi, end_margin, range_margin,
        stuck_duty, stuck_s;
    int stuck_counts;
    int hello_per_tick; /* HELLO authentications allowed per tick (the rest: throttled) */
} Safety;

/* An output attribute kept open (see io_open_out). */
typedef struct {
    int fd;    /* -1: closed */
    int sysfs; /* 1: a sysfs attribute (each write at offset 0 is a new value) */
    int len;   /* length of the text in a regular file (a fake tree) */
} OutFile;

typedef struct {
    /* files */
    char duty[PATHLEN], period[PATHLEN], enable[PATHLEN], dir_value[PATHLEN], dir_direction[PATHLEN], adc[PATHLEN];
    int adc_fd;
    int line_fd;       /* GPIO character-device line handle, or -1 (sysfs) */
    OutFile duty_out;  /* duty_cycle, kept open */
    OutFile dir_out;   /* sysfs DIR value, kept open (fd -1 with a character device) */
    /* state */
    int raw;
    int64_t raw_ok_ns;
    double target, applied; /* [V] */
    int duty_ns, dir_high;  /* last written (-1: unknown, forces a write) */
    int limit;              /* 1 low end, 2 high end */
    int64_t drive_since;
    int drive_raw;
} Leg;

typedef struct {
    uint32_t id;
    HmacKey key;
    int64_t offset_ns; /* daemon time - master time (smallest seen) */
    uint32_t last_seq;
    int64_t t_open;
} Session;

#define PENDING 4 /* challenges handed out and not yet answered */
#define SEEN_HELLOS 64
#define HIST_FINE 256   /* tick-lateness histogram: 1 us bins to 256 us ... */
#define HIST_COARSE 256 /* ... then 16 us bins to 4.35 ms, then one overflow bin */

typedef struct {
    Safety safety;
    Leg legs[LEGS];
    int gpio_chardev;
    int state, faults;
    HmacKey key;
    Session session; /* id 0: none */
    Session pending[PENDING];
    int next_pending;
    uint8_t seen_hello[SEEN_HELLOS][NONCE];
    int n_seen;
    uint32_t next_session;
    int64_t last_cmd_ns, last_apply, last_sample;
    int64_t resample_ns; /* a command samples the ADC again unless the last sample is younger */
    uint64_t counters[C_COUNT];
    int hello_budget;
    char last_error[256];
    /* real-time figures of the session (reset when a session opens) */
    uint32_t hist[HIST_FINE + HIST_COARSE + 1];
    uint64_t hist_n;
    int64_t late_max_ns, late_since_sample_ns;
    uint32_t p50_us, p99_us;
    int64_t cpu_ns_at_open, ticks_at_open;
    uint32_t cpu_per_tick_ns;
    int64_t (*cpu_now)(void); /* process CPU time [ns] (board_main.c) */
    void (*log)(const char *fmt, ...);
} Board;

/* board_io.c */
int io_resolve(Board *b, const char *root, int gpio_mode, char *err, size_t errlen); /* mode 0 auto, 1 sysfs, 2 chardev */
int io_write_int(const char *path, long v);
int io_open_out(OutFile *o, const char *path);
int io_put_int(OutFile *o, long v);
int io_write_text(const char *path, const char *text);
long io_read_int(const char *path, int *ok);
int io_read_adc(Leg *leg, int *raw);
int io_set_dir(Leg *leg, int high);
void io_close(Board *b);

/* board_core.c */
void board_init(Board *b, const uint8_t key[32], uint32_t first_session);
int board_setup_outputs(Board *b);
void board_tick(Board *b, int64_t now, int64_t late_ns);
/* a tick's bookkeeping (count, HELLO budget, lateness statistics) for a command that did the
 * tick's work (sample, checks, outputs) */
void board_count_tick(Board *b, int64_t late_ns);
size_t board_handle(Board *b, const uint8_t *d, size_t n, int64_t now, uint8_t *reply);
void board_zero_outputs(Board *b);
void board_close_outputs(Board *b);
void board_fault(Board *b, int bit, const char *why);
const char *board_state_name(int s);
void board_fault_text(int faults, char *out, size_t n);
int random_bytes(uint8_t *out, size_t n);
#endif
