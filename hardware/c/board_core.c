/* The daemon's protocol, state machine and safety rules (see board.h and hardware/daemon.py).
 *
 *   idle --ARM--> armed --RUN--> running --STOP--> idle;  any --fault--> fault (latched, outputs
 *   zero) --RESET--> idle.   ARM and RUN may come in one command: the master arms at its first
 *   step, so nothing it compiles or loads after initialisation can trip the watchdog.
 *
 * Every tick and command: watchdog (armed or running without a valid command for watchdog_s),
 * clamp to +-v_max, slew limit, end-of-stroke limits (only motion away from an end inside
 * end_margin), ADC stale / out of range / stuck checks; a fault zeroes the outputs.
 *
 * Handshake: HELLO(client nonce) under the shared key gets WELCOME(client nonce, challenge) with
 * a proposed session id, and changes nothing else; the session opens only when a COMMAND
 * authenticated with HMAC(key, "rpr-session" | client nonce | challenge) arrives, so a recorded
 * HELLO replayed later (even after a restart) gets a challenge it cannot answer.  Work per
 * datagram is bounded: cheap checks (length, magic, type, session id, sequence) come first and
 * cost no MAC; each datagram costs at most one MAC (two SHA-256 compressions), and HELLOs are
 * authenticated at most hello_per_tick per tick (the rest are dropped and counted: throttled).
 */
#include <math.h>
#include <stdio.h>
#include <string.h>

#include "board.h"

const char *const COUNTER_NAMES[C_COUNT] = {"received", "commands", "malformed", "unauthenticated", "old_session",
                                            "out_of_sequence", "stale", "refused", "sessions", "faults", "ticks",
                                            "writes", "throttled"};
static const char *const FAULT_NAMES[] = {"watchdog", "non-finite command", "ADC stale", "ADC out of range",
                                          "position stuck while driven", "output write failed", "daemon exception"};

const char *board_state_name(int s) {
    static const char *const names[] = {"idle", "armed", "running", "fault"};
    return s >= 0 && s < 4 ? names[s] : "?";
}

void board_fault_text(int faults, char *out, size_t n) {
    size_t i;
    out[0] = 0;
    for (i = 0; i < sizeof FAULT_NAMES / sizeof *FAULT_NAMES; i++)
        if (faults & (1 << i)) {
            if (out[0]) strncat(out, ", ", n - strlen(out) - 1);
            strncat(out, FAULT_NAMES[i], n - strlen(out) - 1);
        }
    if (!out[0]) snprintf(out, n, "none");
}

static void put16(uint8_t *p, uint32_t v) { p[0] = (uint8_t)v; p[1] = (uint8_t)(v >> 8); }
static void put32(uint8_t *p, uint32_t v) { put16(p, v); put16(p + 2, v >> 16); }
static void put64(uint8_t *p, uint64_t v) { put32(p, (uint32_t)v); put32(p + 4, (uint32_t)(v >> 32)); }
static uint32_t get32(const uint8_t *p) { return (uint32_t)p[0] | (uint32_t)p[1] << 8 | (uint32_t)p[2] << 16 | (uint32_t)p[3] << 24; }
static uint64_t get64(const uint8_t *p) { return (uint64_t)get32(p) | (uint64_t)get32(p + 4) << 32; }

/* Saturating signed 64-bit time arithmetic [ns]: a sender time is data (2^63, -2^63), and an
 * overflow on the staleness check would accept a stale command (issue 33). */
#define FUTURE_NS 10000000000LL /* 10 s: far more than a hello's delay can shift the offset */

static int64_t sat_add(int64_t a, int64_t b) {
    int64_t r;
    return __builtin_add_overflow(a, b, &r) ? (b > 0 ? INT64_MAX : INT64_MIN) : r;
}
static int64_t sat_sub(int64_t a, int64_t b) {
    int64_t r;
    return __builtin_sub_overflow(a, b, &r) ? (b < 0 ? INT64_MAX : INT64_MIN) : r;
}

void board_init(Board *b, const uint8_t key[32], uint32_t first_session) {
    int i;
    Safety s = {BOARD_V_MAX, BOARD_SLEW, BOARD_WATCHDOG_S, BOARD_STALE_MS, BOARD_ADC_STALE_S, BOARD_TRAVEL_LO,
                BOARD_TRAVEL_HI, BOARD_END_MARGIN, BOARD_RANGE_MARGIN, BOARD_STUCK_DUTY, BOARD_STUCK_S,
                BOARD_STUCK_COUNTS, BOARD_HELLO_PER_TICK};
    memset(b, 0, sizeof *b);
    b->safety = s;
    for (i = 0; i < LEGS; i++) {
        b->legs[i].adc_fd = b->legs[i].line_fd = b->legs[i].duty_out.fd = b->legs[i].dir_out.fd = -1;
        b->legs[i].raw = b->legs[i].duty_ns = b->legs[i].dir_high = b->legs[i].drive_raw = -1;
    }
    hmac_key_init(&b->key, key, 32);
    b->next_session = first_session ? first_session : 1;
    b->state = S_IDLE;
    b->hello_budget = s.hello_per_tick;
}

/* --- outputs ------------------------------------------------------------------------------- */
/* duty first when it drops, DIR first when it rises: never drive the old direction harder */
static int write_leg(Board *b, Leg *leg, int duty, int dir_high, int force) {
    int rc = 0;
    if (force || duty != leg->duty_ns) {
        if (io_put_int(&leg->duty_out, duty) != 0) rc = -1;
        else leg->duty_ns = duty;
        b->counters[C_WRITES]++;
    }
    if (force || dir_high != leg->dir_high) {
        if (io_set_dir(leg, dir_high) != 0) rc = -1;
        else leg->dir_high = dir_high;
        b->counters[C_WRITES]++;
    }
    return rc;
}

/* duty 0 and DIR low on every leg (each attempted even if one fails) */
void board_zero_outputs(Board *b) {
    int i, bad = 0;
    for (i = 0; i < LEGS; i++) {
        b->legs[i].target = b->legs[i].applied = 0.0;
        if (write_leg(b, &b->legs[i], 0, 0, 1) != 0) bad = 1;
    }
    if (bad) b->faults |= FB_IO;
}

int board_setup_outputs(Board *b) {
    int i, ok;
    for (i = 0; i < LEGS; i++) {
        Leg *leg = &b->legs[i];
        if (leg->line_fd < 0 && io_write_text(leg->dir_direction, "out") != 0) return -1;
        if (write_leg(b, leg, 0, 0, 1) != 0) return -1;
        if (io_read_int(leg->period, &ok) != BOARD_PERIOD_NS || !ok)
            if (io_write_int(leg->period, BOARD_PERIOD_NS) != 0) return -1;
        if (io_write_int(leg->enable, 1) != 0) return -1;
    }
    return 0;
}

/* zero the outputs, then disable the PWM channels (the way out) */
void board_close_outputs(Board *b) {
    int i;
    board_zero_outputs(b);
    for (i = 0; i < LEGS; i++) io_write_int(b->legs[i].enable, 0);
}

void board_fault(Board *b, int bit, const char *why) {
    int i;
    if (b->state != S_FAULT) {
        char names[128];
        b->counters[C_FAULTS]++;
        board_fault_text(bit, names, sizeof names);
        snprintf(b->last_error, sizeof b->last_error, "%s (%s)", names, why);
        if (b->log) b->log("fault: %s (%s); outputs zeroed, latched until reset", names, why);
    }
    b->faults |= bit;
    b->state = S_FAULT;
    for (i = 0; i < LEGS; i++) {
        b->legs[i].target = b->legs[i].applied = 0.0;
        b->legs[i].drive_since = 0;
    }
    board_zero_outputs(b);
}

static void apply(Board *b, int64_t now) {
    const Safety *s = &b->safety;
    double dt = b->last_apply ? (double)(now - b->last_apply) / 1e9 : 0.0;
    int active = b->state == S_RUNNING, i;
    b->last_apply = now;
    for (i = 0; i < LEGS; i++) {
        Leg *leg = &b->legs[i];
        double want = active ? fmax(-s->v_max, fmin(s->v_max, leg->target)) : 0.0, v, frac;
        int duty;
        leg->limit = 0;
        if (leg->raw >= 0 && leg->raw <= s->travel_lo + s->end_margin && want < 0) {
            want = 0.0;
            leg->limit = 1;
        } else if (leg->raw >= 0 && leg->raw >= s->travel_hi - s->end_margin && want > 0) {
            want = 0.0;
            leg->limit = 2;
        }
        if (!active) {
            v = 0.0;
        } else {
            double step = s->slew * dt;
            v = leg->applied + fmax(-step, fmin(step, want - leg->applied));
            if (want == 0.0 && fabs(v) < 1e-9) v = 0.0;
            if ((leg->limit == 1 && v < 0) || (leg->limit == 2 && v > 0)) v = 0.0; /* at an end: stop at once */
        }
        leg->applied = v;
        /* hardware/convert.py volts_to_drive: |v| / v_max of the period, DIR high for reverse */
        frac = fmin(fabs(v), s->v_max) / s->v_max;
        duty = (int)lround(frac * BOARD_PERIOD_NS);
        if (duty > BOARD_PERIOD_NS) duty = BOARD_PERIOD_NS;
        if (write_leg(b, leg, duty, v < 0 && duty > 0, 0) != 0) {
            board_fault(b, FB_IO, "writing an output failed");
            return;
        }
    }
}

/* --- sensing ------------------------------------------------------------------------------- */
static void sample(Board *b, int64_t now) {
    const Safety *s = &b->safety;
    int i;
    b->last_sample = now;
    for (i = 0; i < LEGS; i++) {
        Leg *leg = &b->legs[i];
        char why[160];
        int raw, driven;
        if (io_read_adc(leg, &raw) != 0) {
            if (leg->raw_ok_ns && now - leg->raw_ok_ns > s->adc_stale_s * 1e9) {
                snprintf(why, sizeof why, "leg %d: ADC unreadable for %.0f ms", i + 1, (double)(now - leg->raw_ok_ns) / 1e6);
                board_fault(b, FB_ADC_STALE, why);
            }
            continue;
        }
        leg->raw = raw;
        leg->raw_ok_ns = now;
        if (raw < s->travel_lo - s->range_margin || raw > s->travel_hi + s->range_margin) {
            snprintf(why, sizeof why, "leg %d: %d counts outside %.0f..%.0f (+-%.0f): sensor unplugged?", i + 1, raw,
                     s->travel_lo, s->travel_hi, s->range_margin);
            board_fault(b, FB_ADC_RANGE, why);
        }
        driven = fabs(leg->applied) >= s->stuck_duty * s->v_max;
        if (!driven) {
            leg->drive_since = 0;
            leg->drive_raw = -1;
        } else if (leg->drive_since == 0) {
            leg->drive_since = now;
            leg->drive_raw = raw;
        } else if (raw - leg->drive_raw > s->stuck_counts || leg->drive_raw - raw > s->stuck_counts) {
            leg->drive_since = now;
            leg->drive_raw = raw;
        } else if (now - leg->drive_since > s->stuck_s * 1e9) {
            snprintf(why, sizeof why, "leg %d: driven at %+.1f V for %.2f s but the position stayed at %d counts",
                     i + 1, leg->applied, s->stuck_s, raw);
            board_fault(b, FB_ADC_STUCK, why);
        }
    }
}

/* --- tick-lateness statistics of the session ----------------------------------------------- */
static void record_late(Board *b, int64_t late_ns) {
    int64_t us = late_ns / 1000;
    int bin;
    if (late_ns < 0) us = 0;
    bin = us < HIST_FINE ? (int)us : us < HIST_FINE + 16 * HIST_COARSE ? HIST_FINE + (int)((us - HIST_FINE) / 16)
                                                                       : HIST_FINE + HIST_COARSE;
    b->hist[bin]++;
    b->hist_n++;
    if (late_ns > b->late_max_ns) b->late_max_ns = late_ns;
    if (late_ns > b->late_since_sample_ns) b->late_since_sample_ns = late_ns;
    if ((b->hist_n & 127) == 0) { /* percentiles and CPU every 128 ticks: a cheap scan */
        uint64_t c = 0, q50 = (b->hist_n + 1) / 2, q99 = b->hist_n - b->hist_n / 100;
        int k, got50 = 0;
        for (k = 0; k <= HIST_FINE + HIST_COARSE; k++) {
            uint32_t upper = k < HIST_FINE ? (uint32_t)k : k < HIST_FINE + HIST_COARSE
                                                               ? (uint32_t)(HIST_FINE + 16 * (k - HIST_FINE) + 15)
                                                               : (uint32_t)(b->late_max_ns / 1000);
            c += b->hist[k];
            if (!got50 && c >= q50) { b->p50_us = upper; got50 = 1; }
            if (c >= q99) { b->p99_us = upper; break; }
        }
        if (b->cpu_now) {
            int64_t ticks = (int64_t)b->counters[C_TICKS] - b->ticks_at_open;
            if (ticks > 0) b->cpu_per_tick_ns = (uint32_t)((b->cpu_now() - b->cpu_ns_at_open) / ticks);
        }
    }
}

void board_count_tick(Board *b, int64_t late_ns) {
    b->counters[C_TICKS]++;
    b->hello_budget = b->safety.hello_per_tick;
    if (b->session.id) record_late(b, late_ns);
}

void board_tick(Board *b, int64_t now, int64_t late_ns) {
    board_count_tick(b, late_ns);
    sample(b, now);
    if ((b->state == S_ARMED || b->state == S_RUNNING) && now - b->last_cmd_ns > b->safety.watchdog_s * 1e9) {
        char why[96];
        snprintf(why, sizeof why, "no valid command for %.3f ms", (double)(now - b->last_cmd_ns) / 1e6);
        board_fault(b, FB_WATCHDOG, why);
    }
    if (b->state != S_FAULT) apply(b, now);
}

/* --- datagrams ----------------------------------------------------------------------------- */
static size_t seal(const HmacKey *k, uint8_t *d, int type, uint32_t session, uint32_t seq, int64_t now, size_t body) {
    d[HDR_MAGIC] = PROTO_MAGIC0; d[HDR_MAGIC + 1] = PROTO_MAGIC1; d[HDR_VERSION] = PROTO_VERSION;
    d[HDR_TYPE] = (uint8_t)type;
    put32(d + HDR_SESSION, session);
    put32(d + HDR_SEQ, seq);
    put64(d + HDR_TIME_NS, (uint64_t)now);
    hmac_key_mac(k, d, HDR + body, d + HDR + body);
    return HDR + body + MAC;
}

static int authentic(const HmacKey *k, const uint8_t *d, size_t n) {
    uint8_t m[32];
    hmac_key_mac(k, d, n - MAC, m);
    return hmac_equal(m, d + n - MAC);
}

static size_t hello(Board *b, const uint8_t *d, int64_t now, uint8_t *reply) {
    uint8_t buf[11 + 2 * NONCE], skey[32];
    Session *p;
    int i;
    if (b->hello_budget <= 0) {
        b->counters[C_THROTTLED]++;
        return 0;
    }
    b->hello_budget--;
    if (!authentic(&b->key, d, HDR + BODY_HELLO + MAC)) {
        b->counters[C_UNAUTHENTICATED]++;
        return 0;
    }
    for (i = 0; i < b->n_seen && i < SEEN_HELLOS; i++)
        if (memcmp(b->seen_hello[i], d + HDR, NONCE) == 0) {
            b->counters[C_OUT_OF_SEQUENCE]++; /* a HELLO replayed within this run */
            return 0;
        }
    if (b->state == S_ARMED || b->state == S_RUNNING) {
        b->counters[C_REFUSED]++; /* one master at a time; a dead one is cut off by the watchdog */
        return 0;
    }
    memcpy(b->seen_hello[b->n_seen % SEEN_HELLOS], d + HDR, NONCE);
    b->n_seen++;
    p = &b->pending[b->next_pending];
    b->next_pending = (b->next_pending + 1) % PENDING;
    memcpy(reply + HDR, d + HDR, NONCE);
    if (random_bytes(reply + HDR + NONCE, NONCE) != 0) {
        board_fault(b, FB_EXCEPTION, "no random bytes for the challenge");
        return 0;
    }
    memcpy(buf, "rpr-session", 11);
    memcpy(buf + 11, d + HDR, NONCE);
    memcpy(buf + 11 + NONCE, reply + HDR + NONCE, NONCE);
    hmac_key_mac(&b->key, buf, sizeof buf, skey);
    memset(p, 0, sizeof *p);
    b->next_session = b->next_session + 1 ? b->next_session + 1 : 1;
    p->id = b->next_session;
    hmac_key_init(&p->key, skey, 32);
    p->offset_ns = sat_sub(now, (int64_t)get64(d + HDR_TIME_NS));
    return seal(&b->key, reply, T_WELCOME, p->id, 0, now, BODY_WELCOME);
}

static void open_session(Board *b, Session *p, int64_t now) {
    b->session = *p;
    b->session.t_open = now;
    memset(p, 0, sizeof *p);
    b->counters[C_SESSIONS]++;
    memset(b->hist, 0, sizeof b->hist);
    b->hist_n = 0;
    b->late_max_ns = b->late_since_sample_ns = 0;
    b->p50_us = b->p99_us = 0;
    b->cpu_ns_at_open = b->cpu_now ? b->cpu_now() : 0;
    b->ticks_at_open = (int64_t)b->counters[C_TICKS];
    b->cpu_per_tick_ns = 0;
    if (b->log) b->log("session %08x opened", (unsigned)b->session.id);
}

static void command(Board *b, int flags, const float *volts, int64_t now) {
    int i;
    if ((flags & F_RESET) && b->state == S_FAULT) {
        char text[128];
        board_fault_text(b->faults, text, sizeof text);
        if (b->log) b->log("fault reset (%s)", text);
        b->state = S_IDLE;
        b->faults = 0;
    }
    if (flags & F_STOP) {
        if (b->state != S_FAULT) b->state = S_IDLE;
        board_zero_outputs(b);
        return;
    }
    if (flags & F_QUERY) return;
    if ((flags & F_ARM) && b->state == S_IDLE) {
        b->state = S_ARMED;
        b->last_cmd_ns = now;
    }
    if (b->state == S_FAULT) {
        b->counters[C_REFUSED]++;
        return;
    }
    if (b->state == S_ARMED || b->state == S_RUNNING) b->last_cmd_ns = now;
    if ((flags & F_RUN) && (b->state == S_ARMED || b->state == S_RUNNING)) {
        char why[96];
        for (i = 0; i < LEGS; i++)
            if (!isfinite(volts[i])) {
                snprintf(why, sizeof why, "command (%g, %g, %g)", volts[0], volts[1], volts[2]);
                board_fault(b, FB_BAD_COMMAND, why);
                return;
            }
        b->state = S_RUNNING;
        for (i = 0; i < LEGS; i++) b->legs[i].target = volts[i];
        if (now - b->last_sample >= b->resample_ns) sample(b, now);
        if (b->state != S_FAULT) apply(b, now);
    }
}

static size_t sample_reply(Board *b, uint32_t seq, int64_t now, uint8_t *reply) {
    uint8_t *p = reply + HDR;
    int i, limits = 0, all_ok = 1;
    int64_t age = 0;
    uint64_t dropped = b->counters[C_MALFORMED] + b->counters[C_UNAUTHENTICATED] + b->counters[C_OLD_SESSION] +
                       b->counters[C_OUT_OF_SEQUENCE] + b->counters[C_STALE] + b->counters[C_THROTTLED];
    memset(p, 0, BODY_SAMPLE);
    p[SAMPLE_STATE] = (uint8_t)b->state;
    for (i = 0; i < LEGS; i++) {
        Leg *leg = &b->legs[i];
        int raw = leg->raw < 0 ? 0 : leg->raw > 65535 ? 65535 : leg->raw;
        limits |= leg->limit << (2 * i);
        put16(p + SAMPLE_RAW + 2 * i, (uint32_t)raw);
        if (!leg->raw_ok_ns) all_ok = 0;
        else if ((now - leg->raw_ok_ns) / 1000 > age) age = (now - leg->raw_ok_ns) / 1000;
    }
    p[SAMPLE_LIMITS] = (uint8_t)limits;
    put16(p + SAMPLE_FAULTS, (uint32_t)b->faults);
    put32(p + SAMPLE_AGE_US, all_ok ? (uint32_t)(age > 0xFFFFFFFFll ? 0xFFFFFFFFll : age) : 0xFFFFFFFFu);
    put32(p + SAMPLE_DROPPED, (uint32_t)dropped);
    put32(p + SAMPLE_LATE_US, (uint32_t)(b->late_since_sample_ns / 1000));
    put32(p + SAMPLE_P50_US, b->p50_us);
    put32(p + SAMPLE_P99_US, b->p99_us);
    put32(p + SAMPLE_MAX_US, (uint32_t)(b->late_max_ns / 1000));
    put32(p + SAMPLE_CPU_NS, b->cpu_per_tick_ns);
    put32(p + SAMPLE_THROTTLED, (uint32_t)b->counters[C_THROTTLED]);
    b->late_since_sample_ns = 0;
    return seal(&b->session.key, reply, T_SAMPLE, b->session.id, seq, now, BODY_SAMPLE);
}

/* Act on one datagram; the reply's length (0: none).  Never fails for bad input. */
size_t board_handle(Board *b, const uint8_t *d, size_t n, int64_t now, uint8_t *reply) {
    uint32_t sid, seq;
    Session *ses = NULL;
    int i, type;
    float volts[LEGS];
    b->counters[C_RECEIVED]++;
    if (n < HDR + MAC || d[HDR_MAGIC] != PROTO_MAGIC0 || d[HDR_MAGIC + 1] != PROTO_MAGIC1 ||
        d[HDR_VERSION] != PROTO_VERSION) {
        b->counters[C_MALFORMED]++;
        return 0;
    }
    type = d[HDR_TYPE];
    if (!((type == T_HELLO && n == HDR + BODY_HELLO + MAC) || (type == T_COMMAND && n == HDR + BODY_COMMAND + MAC))) {
        b->counters[C_MALFORMED]++;
        return 0;
    }
    if (type == T_HELLO) return hello(b, d, now, reply);
    sid = get32(d + HDR_SESSION);
    seq = get32(d + HDR_SEQ);
    if (sid && sid == b->session.id) {
        ses = &b->session;
    } else if (sid) {
        for (i = 0; i < PENDING; i++)
            if (b->pending[i].id == sid) ses = &b->pending[i];
    }
    if (!ses) {
        b->counters[C_OLD_SESSION]++;
        return 0;
    }
    if (seq <= ses->last_seq) { /* before the MAC: a replay costs nothing */
        b->counters[C_OUT_OF_SEQUENCE]++;
        return 0;
    }
    if (!authentic(&ses->key, d, n)) {
        b->counters[C_UNAUTHENTICATED]++;
        return 0;
    }
    if (ses != &b->session) { /* the answer to a challenge: the session opens now */
        if (b->state == S_ARMED || b->state == S_RUNNING) {
            b->counters[C_REFUSED]++;
            return 0;
        }
        open_session(b, ses, now);
        ses = &b->session;
    }
    {
        int64_t t = (int64_t)get64(d + HDR_TIME_NS), late = sat_sub(now, sat_add(t, ses->offset_ns));
        /* a negative sender time (a monotonic clock never is), or one more than FUTURE_NS ahead
         * of what the session's offset predicts, is refused as stale and moves no offset */
        if (t < 0 || late > b->safety.stale_ms * 1e6 || late < -FUTURE_NS) {
            b->counters[C_STALE]++;
            ses->last_seq = seq;
            return 0;
        }
        if (sat_sub(now, t) < ses->offset_ns) ses->offset_ns = sat_sub(now, t);
    }
    ses->last_seq = seq;
    b->counters[C_COMMANDS]++;
    for (i = 0; i < LEGS; i++) {
        uint32_t u = get32(d + HDR + COMMAND_VOLTS + 4 * i);
        memcpy(&volts[i], &u, 4);
    }
    command(b, d[HDR + COMMAND_FLAGS], volts, now);
    return sample_reply(b, seq, now, reply);
}
