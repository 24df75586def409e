/* The hardware FMU: FMI 2.0 co-simulation over the rig's I/O daemon (hardware/c/board_*.c).
 *
 * Each doStep sends one authenticated COMMAND (the three leg voltages) to the board and waits,
 * up to `timeout` seconds, for its SAMPLE (three raw ADC counts, state, faults); the outputs are
 * that sample, converted by the two-point calibration of each leg, and the board's own real-time
 * figures of the session (tick lateness, CPU per tick, datagrams dropped and throttled).  A silent board (timeout,
 * refused connection) or a board in fault makes doStep return fmi2Error with the reason logged.
 * The rig cannot go back in time: canGetAndSetFMUstate is false and the state functions fail.
 *
 * Protocol (little-endian, see hardware/protocol.py): header "RP", version, type, session (u32),
 * sequence (u32), time (u64 ns); body; HMAC-SHA256 over header and body.  The session key is
 * HMAC(key, "rpr-session" | client nonce | the board's challenge); the session opens with the
 * first command under it.
 *
 * Life cycle: fmi2EnterInitializationMode connects (HELLO/WELCOME) and reads a first sample
 * (QUERY), so the outputs are the rig's at t0; the board stays idle (no watchdog) until the first
 * doStep, whose command arms and runs it at once: whatever the master compiles or loads between
 * initialisation and its first step cannot trip the 100 ms watchdog.  fmi2Terminate and
 * fmi2FreeInstance stop it (outputs zero, no fault).
 */
#define _POSIX_C_SOURCE 200112L
#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <netdb.h>
#include <poll.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/types.h>
#include <time.h>
#include <unistd.h>

#include "fmi2Functions.h"
#include "hil_config.h"
#include "hmac_sha256.h"

/* value references (modelDescription.xml is generated from hardware/hil_fmu.py with the same table) */
enum {
    VR_U = 0,            /* 0..2  leg[i].u          input  [V]     */
    VR_S = 3,            /* 3..5  leg[i].s          output [m]     */
    VR_STROKE = 6,       /* 6..8  leg[i].stroke     output [m]     */
    VR_RAW = 9,          /* 9..11 leg[i].raw        output [counts] */
    VR_AGE = 12,         /* sample_age output [s] */
    VR_FAULT = 13,       /* fault bits output */
    VR_STATE = 14,       /* board state output */
    VR_RTT = 15,         /* round_trip output [s] */
    VR_TIMEOUT = 16,     /* timeout parameter [s] */
    VR_RAW_ZERO = 17,    /* 17..19 leg[i].raw_zero parameter */
    VR_RAW_FULL = 20,    /* 20..22 leg[i].raw_full parameter */
    VR_STROKE_FULL = 23, /* 23..25 leg[i].stroke_full parameter [m] */
    VR_S_OFFSET = 26,    /* 26..28 leg[i].s_offset parameter [m] */
    VR_TICK_LATE = 29,   /* board_tick_late output [s]: largest tick lateness since the last step */
    VR_TICK_P50 = 30,    /* board_tick_p50 output [s] (session) */
    VR_TICK_P99 = 31,    /* board_tick_p99 output [s] (session) */
    VR_TICK_MAX = 32,    /* board_tick_max output [s] (session) */
    VR_CPU_TICK = 33,    /* board_cpu_per_tick output [s] (session mean) */
    VR_DROPPED = 34,     /* board_dropped output: datagrams the board dropped */
    VR_THROTTLED = 35,   /* board_throttled output: of those, unauthenticated beyond its budget */
    NR = 36
};
enum { VB_RESET = 0, NB = 1 };
enum { VS_ADDRESS = 0, VS_KEYFILE = 1, NS = 2 };

#include "board_protocol.h" /* the protocol's constants, generated from hardware/protocol.py */

typedef enum { ST_INSTANTIATED, ST_INIT, ST_STEP, ST_TERMINATED, ST_ERROR } Phase;

typedef struct {
    fmi2CallbackLogger logger;
    fmi2ComponentEnvironment env;
    char name[128];
    int logging;
    Phase phase;
    double r[NR];
    fmi2Boolean b[NB];
    char address[256];
    char keyfile[1024];
    int sock;
    uint8_t key[32], skey[32];
    uint32_t session, seq;
    int connected, armed;
    double time;
} Hil;

static const char *const FAULTS[] = {"watchdog", "non-finite command", "ADC stale", "ADC out of range",
                                     "position stuck while driven", "output write failed", "daemon exception"};

static void say(Hil *h, fmi2Status status, const char *category, const char *fmt, ...) {
    char buf[768];
    va_list ap;
    size_t i;
    if (!h->logger) return;
    if (status == fmi2OK && !h->logging) return;
    va_start(ap, fmt);
    vsnprintf(buf, sizeof buf, fmt, ap);
    va_end(ap);
    for (i = 0; buf[i]; i++)
        if (buf[i] == '%') buf[i] = '#'; /* the message is no format string */
    h->logger(h->env, h->name, status, category, buf);
}

static uint64_t now_ns(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (uint64_t)ts.tv_sec * 1000000000ull + (uint64_t)ts.tv_nsec;
}

static void put16(uint8_t *p, uint16_t v) { p[0] = (uint8_t)v; p[1] = (uint8_t)(v >> 8); }
static void put32(uint8_t *p, uint32_t v) { put16(p, (uint16_t)v); put16(p + 2, (uint16_t)(v >> 16)); }
static void put64(uint8_t *p, uint64_t v) { put32(p, (uint32_t)v); put32(p + 4, (uint32_t)(v >> 32)); }
static uint16_t get16(const uint8_t *p) { return (uint16_t)(p[0] | p[1] << 8); }
static uint32_t get32(const uint8_t *p) { return (uint32_t)get16(p) | (uint32_t)get16(p + 2) << 16; }

static size_t header(uint8_t *p, int type, uint32_t session, uint32_t seq) {
    p[HDR_MAGIC] = PROTO_MAGIC0; p[HDR_MAGIC + 1] = PROTO_MAGIC1; p[HDR_VERSION] = PROTO_VERSION;
    p[HDR_TYPE] = (uint8_t)type;
    put32(p + HDR_SESSION, session);
    put32(p + HDR_SEQ, seq);
    put64(p + HDR_TIME_NS, now_ns());
    return HDR;
}

static int check_mac(const uint8_t *key, const uint8_t *d, size_t n) {
    uint8_t m[32];
    if (n < HDR + MAC) return 0;
    hmac_sha256(key, 32, d, n - MAC, m);
    return hmac_equal(m, d + n - MAC);
}

static int random_bytes(uint8_t *out, size_t n) {
    int fd = open("/dev/urandom", O_RDONLY);
    size_t got = 0;
    if (fd < 0) return -1;
    while (got < n) {
        ssize_t k = read(fd, out + got, n - got);
        if (k <= 0) { close(fd); return -1; }
        got += (size_t)k;
    }
    close(fd);
    return 0;
}

/* --- key and socket ---------------------------------------------------------------------- */
static int read_key(Hil *h) {
    FILE *f;
    char text[130], path[1280];
    struct stat sb;
    size_t n, i;
    const char *home = getenv("HOME");
    if (h->keyfile[0] == '~' && h->keyfile[1] == '/' && home) /* ~/ as in a shell */
        snprintf(path, sizeof path, "%s%s", home, h->keyfile + 1);
    else
        snprintf(path, sizeof path, "%s", h->keyfile);
    if (stat(path, &sb) != 0) {
        say(h, fmi2Error, "logStatusError", "key file '%s': %s", h->keyfile, strerror(errno));
        return -1;
    }
    if (sb.st_mode & 077) {
        say(h, fmi2Error, "logStatusError", "key file '%s' is readable by others; chmod 600 it", h->keyfile);
        return -1;
    }
    f = fopen(path, "r");
    if (!f) {
        say(h, fmi2Error, "logStatusError", "key file '%s': %s", h->keyfile, strerror(errno));
        return -1;
    }
    n = fread(text, 1, sizeof text - 1, f);
    fclose(f);
    text[n] = 0;
    while (n && (text[n - 1] == '\n' || text[n - 1] == '\r' || text[n - 1] == ' ')) text[--n] = 0;
    if (n != 64) {
        say(h, fmi2Error, "logStatusError", "key file '%s': expected 64 hex digits (rpr-cosim board keygen)", h->keyfile);
        return -1;
    }
    for (i = 0; i < 32; i++) {
        unsigned v;
        if (sscanf(text + 2 * i, "%2x", &v) != 1) {
            say(h, fmi2Error, "logStatusError", "key file '%s': not hexadecimal", h->keyfile);
            return -1;
        }
        h->key[i] = (uint8_t)v;
    }
    return 0;
}

static int open_socket(Hil *h) {
    char host[256], *colon;
    const char *port;
    struct addrinfo hints, *res = NULL;
    int rc, s;
    strncpy(host, h->address, sizeof host - 1);
    host[sizeof host - 1] = 0;
    colon = strrchr(host, ':');
    if (!colon || colon == host || !colon[1]) {
        say(h, fmi2Error, "logStatusError", "address '%s': expected HOST:PORT, e.g. 127.0.0.1:5005", h->address);
        return -1;
    }
    *colon = 0;
    port = colon + 1;
    memset(&hints, 0, sizeof hints);
    hints.ai_family = AF_INET;
    hints.ai_socktype = SOCK_DGRAM;
    rc = getaddrinfo(host, port, &hints, &res);
    if (rc != 0 || !res) {
        say(h, fmi2Error, "logStatusError", "address '%s': %s", h->address, gai_strerror(rc));
        return -1;
    }
    s = socket(res->ai_family, res->ai_socktype, res->ai_protocol);
    if (s < 0 || connect(s, res->ai_addr, res->ai_addrlen) != 0) {
        say(h, fmi2Error, "logStatusError", "board at %s: %s", h->address, strerror(errno));
        if (s >= 0) close(s);
        freeaddrinfo(res);
        return -1;
    }
    freeaddrinfo(res);
    h->sock = s;
    return 0;
}

/* Wait for a datagram of `type` (and a sequence number seq..seq_hi unless seq is 0) authenticated
 * with `key`; 0 ok, -1 timeout, -2 refused/socket error (reason logged by the caller from errno). */
static int await_range(Hil *h, int type, uint32_t seq, uint32_t seq_hi, const uint8_t *key, uint8_t *buf, size_t want,
                       double timeout_s) {
    uint64_t deadline = now_ns() + (uint64_t)(timeout_s * 1e9);
    int last = 0;
    for (;;) {
        uint64_t t = now_ns();
        struct pollfd pfd;
        ssize_t n;
        int ms, ready;
        /* past the deadline, still read what has arrived (this process may have been descheduled
         * while the answer came): only an empty socket then is a timeout */
        if (t >= deadline) last = 1;
        ms = last ? 0 : (int)((deadline - t + 999999) / 1000000);
        pfd.fd = h->sock;
        pfd.events = POLLIN;
        pfd.revents = 0;
        ready = poll(&pfd, 1, ms);
        if (ready < 0) {
            if (errno == EINTR) continue;
            return -2;
        }
        if (!(pfd.revents & (POLLIN | POLLERR))) {
            if (last) return -1;
            continue;
        }
        n = recv(h->sock, buf, 256, 0);
        if (n < 0) {
            if (errno == EINTR || errno == EAGAIN) continue;
            return -2;
        }
        if ((size_t)n != want || buf[HDR_MAGIC] != PROTO_MAGIC0 || buf[HDR_MAGIC + 1] != PROTO_MAGIC1 ||
            buf[HDR_VERSION] != PROTO_VERSION || buf[HDR_TYPE] != type) continue;
        if (seq && (get32(buf + HDR_SEQ) < seq || get32(buf + HDR_SEQ) > seq_hi)) continue; /* an older command's */
        if (!check_mac(key, buf, (size_t)n)) continue;
        return 0;
    }
}

static void silent(Hil *h, int rc, const char *what) {
    if (rc == -1)
        say(h, fmi2Error, "logStatusError", "board at %s silent: no %s within %.0f ms (daemon not running, "
            "unreachable, or a different key?)", h->address, what, h->r[VR_TIMEOUT] * 1e3);
    else
        say(h, fmi2Error, "logStatusError", "board at %s: %s while waiting for %s", h->address, strerror(errno), what);
}

static int hello(Hil *h) {
    uint8_t d[HDR + NONCE + MAC], r[256], nonce[NONCE], buf[11 + 2 * NONCE];
    int rc;
    if (random_bytes(nonce, NONCE) != 0) {
        say(h, fmi2Error, "logStatusError", "cannot read /dev/urandom for the session nonce");
        return -1;
    }
    header(d, T_HELLO, 0, 0);
    memcpy(d + HDR, nonce, NONCE);
    hmac_sha256(h->key, 32, d, HDR + NONCE, d + HDR + NONCE);
    /* the same HELLO again every 5 ms until the timeout: a board under a flood authenticates only
     * a few HELLOs per tick, and one it dropped unread it will read the next time */
    {
        uint64_t end = now_ns() + (uint64_t)(h->r[VR_TIMEOUT] * 1e9);
        for (;;) {
            uint64_t t = now_ns();
            double slice = t >= end ? 0 : (double)(end - t) / 1e9;
            if (slice <= 0) {
                silent(h, -1, "WELCOME to HELLO (a board in use by another master refuses it)");
                return -1;
            }
            if (send(h->sock, d, sizeof d, 0) < 0) {
                silent(h, -2, "WELCOME");
                return -1;
            }
            rc = await_range(h, T_WELCOME, 0, 0, h->key, r, HDR + BODY_WELCOME + MAC, slice < 0.005 ? slice : 0.005);
            if (rc == -2) {
                silent(h, rc, "WELCOME to HELLO");
                return -1;
            }
            if (rc == 0 && memcmp(r + HDR, nonce, NONCE) == 0) break;
        }
    }
    h->session = get32(r + HDR_SESSION);
    memcpy(buf, "rpr-session", 11);
    memcpy(buf + 11, nonce, NONCE);
    memcpy(buf + 11 + NONCE, r + HDR + NONCE, NONCE);
    hmac_sha256(h->key, 32, buf, sizeof buf, h->skey);
    h->seq = 0;
    say(h, fmi2OK, "logCalls", "session %08x with the board at %s", (unsigned)h->session, h->address);
    return 0;
}

/* One command/sample exchange; updates the outputs.  0 ok, -1 failed (logged). */
static int exchange(Hil *h, int flags, const double *volts) {
    uint8_t d[HDR + BODY_COMMAND + MAC], r[256];
    static const int fig[] = {VR_TICK_LATE, VR_TICK_P50, VR_TICK_P99, VR_TICK_MAX};
    uint64_t t0;
    int i, rc, state, faults;
    double rtt;
    uint32_t first = h->seq + 1;
    uint64_t end;
    /* the same command under a new sequence number every 5 ms until the timeout: a datagram lost
     * (a full socket queue under a flood, a lossy link) costs 5 ms, not the run; commands are
     * idempotent (target voltages, ARM once idle, STOP, RESET), and a SAMPLE of any of them answers */
    t0 = now_ns();
    end = t0 + (uint64_t)(h->r[VR_TIMEOUT] * 1e9);
    for (;;) {
        uint64_t t = now_ns();
        double slice = t >= end ? 0 : (double)(end - t) / 1e9;
        if (slice <= 0) {
            silent(h, -1, "SAMPLE");
            return -1;
        }
        header(d, T_COMMAND, h->session, ++h->seq);
        memset(d + HDR, 0, BODY_COMMAND);
        d[HDR + COMMAND_FLAGS] = (uint8_t)flags;
        for (i = 0; i < 3; i++) {
            float f = (float)volts[i];
            uint32_t u;
            memcpy(&u, &f, 4);
            put32(d + HDR + COMMAND_VOLTS + 4 * i, u);
        }
        hmac_sha256(h->skey, 32, d, HDR + BODY_COMMAND, d + HDR + BODY_COMMAND);
        if (send(h->sock, d, sizeof d, 0) < 0) {
            silent(h, -2, "SAMPLE");
            return -1;
        }
        rc = await_range(h, T_SAMPLE, first, h->seq, h->skey, r, HDR + BODY_SAMPLE + MAC, slice < 0.005 ? slice : 0.005);
        if (rc == 0) break;
        if (rc == -2) {
            silent(h, rc, "SAMPLE");
            return -1;
        }
    }
    rtt = (double)(now_ns() - t0) / 1e9;
    state = r[HDR + SAMPLE_STATE];
    faults = get16(r + HDR + SAMPLE_FAULTS);
    for (i = 0; i < 3; i++) {
        double raw = get16(r + HDR + SAMPLE_RAW + 2 * i);
        double span = h->r[VR_RAW_FULL + i] - h->r[VR_RAW_ZERO + i];
        double stroke = span != 0 ? (raw - h->r[VR_RAW_ZERO + i]) * h->r[VR_STROKE_FULL + i] / span : NAN;
        h->r[VR_RAW + i] = raw;
        h->r[VR_STROKE + i] = stroke;
        h->r[VR_S + i] = h->r[VR_S_OFFSET + i] + stroke;
    }
    h->r[VR_AGE] = get32(r + HDR + SAMPLE_AGE_US) / 1e6 + rtt / 2;
    h->r[VR_FAULT] = faults;
    h->r[VR_STATE] = state;
    h->r[VR_RTT] = rtt;
    h->r[VR_DROPPED] = get32(r + HDR + SAMPLE_DROPPED);
    for (i = 0; i < 4; i++) h->r[fig[i]] = get32(r + HDR + SAMPLE_LATE_US + 4 * i) / 1e6;
    h->r[VR_CPU_TICK] = get32(r + HDR + SAMPLE_CPU_NS) / 1e9;
    h->r[VR_THROTTLED] = get32(r + HDR + SAMPLE_THROTTLED);
    if (state == S_FAULT) {
        char text[256] = "";
        for (i = 0; i < 7; i++)
            if (faults & (1 << i)) {
                if (text[0]) strcat(text, ", ");
                strcat(text, FAULTS[i]);
            }
        say(h, fmi2Error, "logStatusError", "board at %s is in fault (%s): motors stopped, the fault stays latched "
            "until cleared; check the rig, then run again with --set components.%s.params.reset_fault=true",
            h->address, text[0] ? text : "unknown", h->name);
        return -1;
    }
    return 0;
}

static void disconnect(Hil *h) {
    static const double zero[3] = {0, 0, 0};
    if (h->connected) {
        double keep = h->r[VR_TIMEOUT];
        h->r[VR_TIMEOUT] = keep < 0.05 ? keep : 0.05;
        exchange(h, F_STOP, zero); /* outputs zero, state idle (a latched fault stays) */
        h->r[VR_TIMEOUT] = keep;
    }
    if (h->sock >= 0) close(h->sock);
    h->sock = -1;
    h->connected = 0;
}

static int connect_board(Hil *h) {
    static const double zero[3] = {0, 0, 0};
    if (read_key(h) != 0 || open_socket(h) != 0) return -1;
    if (hello(h) != 0) return -1;
    h->connected = 1;
    return exchange(h, F_QUERY | (h->b[VB_RESET] ? F_RESET : 0), zero);
}

/* --- FMI 2.0 ----------------------------------------------------------------------------- */
#define H ((Hil *)c)
#define NEED(c) do { if (!(c)) return fmi2Error; } while (0)

static void defaults(Hil *h) {
    int i;
    memset(h->r, 0, sizeof h->r);
    h->r[VR_TIMEOUT] = HIL_TIMEOUT;
    h->r[VR_STATE] = S_IDLE;
    for (i = 0; i < 3; i++) {
        h->r[VR_RAW_ZERO + i] = HIL_RAW_ZERO;
        h->r[VR_RAW_FULL + i] = HIL_RAW_FULL;
        h->r[VR_STROKE_FULL + i] = HIL_STROKE_FULL;
        h->r[VR_S_OFFSET + i] = HIL_S_OFFSET;
    }
    h->b[VB_RESET] = fmi2False;
    strncpy(h->address, HIL_ADDRESS, sizeof h->address - 1);
    strncpy(h->keyfile, HIL_KEY_FILE, sizeof h->keyfile - 1);
}

const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }
const char *fmi2GetVersion(void) { return fmi2Version; }

fmi2Component fmi2Instantiate(fmi2String name, fmi2Type type, fmi2String guid, fmi2String resources,
                              const fmi2CallbackFunctions *f, fmi2Boolean visible, fmi2Boolean logging) {
    Hil *h;
    (void)resources; (void)visible;
    if (!f || !f->logger) return NULL;
    if (type != fmi2CoSimulation) {
        f->logger(f->componentEnvironment, name, fmi2Error, "logStatusError", "the hardware FMU is co-simulation only");
        return NULL;
    }
    if (!guid || strcmp(guid, HIL_GUID) != 0) {
        f->logger(f->componentEnvironment, name, fmi2Error, "logStatusError", "wrong GUID for this hardware FMU");
        return NULL;
    }
    h = (Hil *)calloc(1, sizeof(Hil));
    if (!h) return NULL;
    h->logger = f->logger;
    h->env = f->componentEnvironment;
    strncpy(h->name, name ? name : "hil", sizeof h->name - 1);
    h->logging = logging;
    h->sock = -1;
    h->phase = ST_INSTANTIATED;
    defaults(h);
    return h;
}

void fmi2FreeInstance(fmi2Component c) {
    if (!c) return;
    disconnect(H);
    free(c);
}

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean on, size_t n, const fmi2String cats[]) {
    (void)n; (void)cats;
    NEED(c);
    H->logging = on;
    return fmi2OK;
}

fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean tolDefined, fmi2Real tol, fmi2Real start,
                               fmi2Boolean stopDefined, fmi2Real stop) {
    (void)tolDefined; (void)tol; (void)stopDefined; (void)stop;
    NEED(c);
    H->time = start;
    return fmi2OK;
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c) {
    NEED(c);
    H->phase = ST_INIT;
    if (connect_board(H) != 0) {
        H->phase = ST_ERROR;
        return fmi2Error;
    }
    return fmi2OK;
}

fmi2Status fmi2ExitInitializationMode(fmi2Component c) {
    NEED(c);
    if (H->phase != ST_INIT || !H->connected) return fmi2Error;
    H->phase = ST_STEP; /* the board stays idle: the first doStep arms it */
    H->armed = 0;
    return fmi2OK;
}

fmi2Status fmi2Terminate(fmi2Component c) {
    NEED(c);
    disconnect(H);
    H->phase = ST_TERMINATED;
    return fmi2OK;
}

fmi2Status fmi2Reset(fmi2Component c) {
    NEED(c);
    disconnect(H);
    defaults(H);
    H->phase = ST_INSTANTIATED;
    return fmi2OK;
}

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2Real v[]) {
    size_t i;
    NEED(c);
    for (i = 0; i < n; i++) {
        if (vr[i] >= NR) return fmi2Error;
        v[i] = H->r[vr[i]];
    }
    return fmi2OK;
}

fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2Real v[]) {
    size_t i;
    NEED(c);
    for (i = 0; i < n; i++) {
        fmi2ValueReference r = vr[i];
        int input = r < VR_S, param = r >= VR_TIMEOUT && r < VR_TICK_LATE;
        if (!input && !param) {
            say(H, fmi2Error, "logStatusError", "value reference %u is an output and cannot be set", (unsigned)r);
            return fmi2Error;
        }
        if (param && H->phase == ST_STEP) {
            say(H, fmi2Error, "logStatusError", "parameters are fixed after initialisation (value reference %u)",
                (unsigned)r);
            return fmi2Error;
        }
        if (r == VR_TIMEOUT && !(v[i] > 0 && v[i] < 10)) {
            say(H, fmi2Error, "logStatusError", "timeout = %g s: expected 0 < timeout < 10", v[i]);
            return fmi2Error;
        }
        H->r[r] = v[i];
    }
    return fmi2OK;
}

fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2Integer v[]) {
    (void)vr; (void)v;
    NEED(c);
    return n ? fmi2Error : fmi2OK;
}
fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2Integer v[]) {
    (void)vr; (void)v;
    NEED(c);
    return n ? fmi2Error : fmi2OK;
}

fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2Boolean v[]) {
    size_t i;
    NEED(c);
    for (i = 0; i < n; i++) {
        if (vr[i] >= NB) return fmi2Error;
        v[i] = H->b[vr[i]];
    }
    return fmi2OK;
}
fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2Boolean v[]) {
    size_t i;
    NEED(c);
    for (i = 0; i < n; i++) {
        if (vr[i] >= NB || H->phase == ST_STEP) return fmi2Error;
        H->b[vr[i]] = v[i];
    }
    return fmi2OK;
}

fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2String v[]) {
    size_t i;
    NEED(c);
    for (i = 0; i < n; i++) {
        if (vr[i] == VS_ADDRESS) v[i] = H->address;
        else if (vr[i] == VS_KEYFILE) v[i] = H->keyfile;
        else return fmi2Error;
    }
    return fmi2OK;
}
fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2String v[]) {
    size_t i;
    NEED(c);
    for (i = 0; i < n; i++) {
        char *dst = vr[i] == VS_ADDRESS ? H->address : vr[i] == VS_KEYFILE ? H->keyfile : NULL;
        size_t cap = vr[i] == VS_ADDRESS ? sizeof H->address : sizeof H->keyfile;
        if (!dst || !v[i] || H->phase == ST_STEP || strlen(v[i]) >= cap) return fmi2Error;
        strcpy(dst, v[i]);
    }
    return fmi2OK;
}

fmi2Status fmi2DoStep(fmi2Component c, fmi2Real t, fmi2Real h, fmi2Boolean noSetPrior) {
    double u[3];
    int i;
    (void)noSetPrior;
    NEED(c);
    if (H->phase != ST_STEP || !H->connected) {
        say(H, fmi2Error, "logStatusError", "doStep outside step mode or without a board session");
        return fmi2Error;
    }
    for (i = 0; i < 3; i++) u[i] = H->r[VR_U + i];
    if (exchange(H, F_RUN | (H->armed ? 0 : F_ARM), u) != 0) {
        H->phase = ST_ERROR;
        return fmi2Error;
    }
    H->armed = 1;
    H->time = t + h;
    return fmi2OK;
}

fmi2Status fmi2CancelStep(fmi2Component c) { NEED(c); return fmi2Error; }

fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind s, fmi2Status *v) {
    (void)s; (void)v;
    NEED(c);
    return fmi2Discard;
}
fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind s, fmi2Real *v) {
    NEED(c);
    if (s == fmi2LastSuccessfulTime) { *v = H->time; return fmi2OK; }
    return fmi2Discard;
}
fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind s, fmi2Integer *v) {
    (void)s; (void)v;
    NEED(c);
    return fmi2Discard;
}
fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind s, fmi2Boolean *v) {
    NEED(c);
    if (s == fmi2Terminated) { *v = fmi2False; return fmi2OK; }
    return fmi2Discard;
}
fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind s, fmi2String *v) {
    (void)s; (void)v;
    NEED(c);
    return fmi2Discard;
}

/* the rig cannot be rolled back: no FMU state */
fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *s) {
    (void)s;
    NEED(c);
    say(H, fmi2Error, "logStatusError", "the hardware cannot go back in time (canGetAndSetFMUstate=false)");
    return fmi2Error;
}
fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate s) { (void)s; return fmi2GetFMUstate(c, NULL); }
fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *s) { (void)s; return fmi2GetFMUstate(c, NULL); }
fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate s, size_t *n) {
    (void)s; (void)n;
    return fmi2GetFMUstate(c, NULL);
}
fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate s, fmi2Byte b[], size_t n) {
    (void)s; (void)b; (void)n;
    return fmi2GetFMUstate(c, NULL);
}
fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte b[], size_t n, fmi2FMUstate *s) {
    (void)b; (void)n; (void)s;
    return fmi2GetFMUstate(c, NULL);
}
fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference u[], size_t nu,
                                        const fmi2ValueReference z[], size_t nz, const fmi2Real dv[], fmi2Real dz[]) {
    (void)u; (void)nu; (void)z; (void)nz; (void)dv; (void)dz;
    NEED(c);
    return fmi2Error;
}
fmi2Status fmi2SetRealInputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                                       const fmi2Integer order[], const fmi2Real v[]) {
    (void)vr; (void)n; (void)order; (void)v;
    NEED(c);
    return fmi2Error;
}
fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                                        const fmi2Integer order[], fmi2Real v[]) {
    (void)vr; (void)n; (void)order; (void)v;
    NEED(c);
    return fmi2Error;
}
