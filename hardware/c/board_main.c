/* rpr-board: the rig's I/O daemon (command line, key, socket, periodic loop, signals).
 *
 *   rpr-board --key FILE [--root /] [--listen 127.0.0.1:5005] [--rate 1000] [--duration S]
 *             [--rt-priority P] [--gpio auto|sysfs|chardev] [--travel LO,HI] [-v] [--step]
 *
 * The loop: a timerfd on an absolute CLOCK_MONOTONIC schedule fires the ticks (no drift, no timer
 * slack); between ticks datagrams are handled one by one, and a due tick always goes first.
 * A RUN command samples the ADC, checks and writes the outputs itself, so while a master drives
 * at the board's rate its commands are the ticks (as a drive in a fieldbus's frame-synchronous
 * mode cycles on the frames): the timer is then moved to 1.5 periods after each command and
 * fires only when the master is late, so the watchdog and the checks never wait longer.  One
 * wake-up per period instead of two.  Each tick's lateness (against the schedule, or for a
 * command against the previous tick plus one period) and the process CPU time per tick are
 * measured and sent back in every SAMPLE.  SIGTERM, SIGINT and SIGHUP end the loop at once (poll is
 * interrupted); the outputs are then zeroed and the PWM disabled.  A crash (SIGSEGV, SIGBUS,
 * SIGFPE, SIGILL, SIGABRT) zeroes the outputs from the signal handler with plain system calls
 * before the process dies.  Only SIGKILL leaves the outputs as they were (see the README: the
 * drivers' inputs are pulled down so that a dead board stops the motors).
 *
 * --step is the test harness: no socket and no clock; lines on stdin drive the daemon with
 * synthetic times ("T now_ns", "D now_ns hex", "S", "C"), answers on stdout.
 */
#define _GNU_SOURCE
#include <arpa/inet.h>
#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <netinet/in.h>
#include <poll.h>
#include <sched.h>
#include <signal.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/ioctl.h>
#include <sys/mman.h>
#include <sys/prctl.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/timerfd.h>
#include <time.h>
#include <unistd.h>
#include <linux/gpio.h>

#include "board.h"

static Board g_board;
static volatile sig_atomic_t g_stop;
static int g_verbose;

static int64_t now_ns(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000ll + ts.tv_nsec;
}

static int64_t cpu_ns(void) {
    struct timespec ts;
    clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
    return (int64_t)ts.tv_sec * 1000000000ll + ts.tv_nsec;
}

static void say(const char *fmt, ...) {
    va_list ap;
    fputs("[board] ", stderr);
    va_start(ap, fmt);
    vfprintf(stderr, fmt, ap);
    va_end(ap);
    fputc('\n', stderr);
    fflush(stderr);
}

static void log_info(const char *fmt, ...) {
    va_list ap;
    char buf[512];
    va_start(ap, fmt);
    vsnprintf(buf, sizeof buf, fmt, ap);
    va_end(ap);
    if (g_verbose || strncmp(buf, "fault:", 6) == 0) say("%s", buf);
}

static int fail(int code, const char *fmt, ...) {
    va_list ap;
    fputs("rpr-board: error: ", stderr);
    va_start(ap, fmt);
    vfprintf(stderr, fmt, ap);
    va_end(ap);
    fputc('\n', stderr);
    return code;
}

/* --- signals ------------------------------------------------------------------------------- */
static void on_stop(int sig) { g_stop = sig; }

/* a crash: zero the outputs with system calls only, then die of the same signal */
static void on_crash(int sig) {
    int i;
    for (i = 0; i < LEGS; i++) {
        Leg *leg = &g_board.legs[i];
        int fd = open(leg->duty, O_WRONLY | O_TRUNC);
        if (fd >= 0) { (void)!write(fd, "0", 1); close(fd); }
        if (leg->line_fd >= 0) {
            struct gpiohandle_data data;
            memset(&data, 0, sizeof data);
            ioctl(leg->line_fd, GPIOHANDLE_SET_LINE_VALUES_IOCTL, &data);
        } else if (leg->dir_value[0]) {
            fd = open(leg->dir_value, O_WRONLY | O_TRUNC);
            if (fd >= 0) { (void)!write(fd, "0", 1); close(fd); }
        }
    }
    signal(sig, SIG_DFL);
    raise(sig);
}

static void install_signals(void) {
    struct sigaction sa;
    int stops[] = {SIGTERM, SIGINT, SIGHUP}, crashes[] = {SIGSEGV, SIGBUS, SIGFPE, SIGILL, SIGABRT};
    size_t i;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_stop; /* no SA_RESTART: poll returns EINTR at once */
    sigemptyset(&sa.sa_mask);
    for (i = 0; i < sizeof stops / sizeof *stops; i++) sigaction(stops[i], &sa, NULL);
    sa.sa_handler = on_crash;
    sa.sa_flags = SA_RESETHAND;
    for (i = 0; i < sizeof crashes / sizeof *crashes; i++) sigaction(crashes[i], &sa, NULL);
    signal(SIGPIPE, SIG_IGN);
}

/* --- key ----------------------------------------------------------------------------------- */
static int read_key(const char *path, uint8_t key[32]) {
    struct stat sb;
    char text[130];
    int fd, i;
    ssize_t n;
    if (stat(path, &sb) != 0) return fail(2, "key file %s: %s", path, strerror(errno));
    if (sb.st_mode & 077)
        return fail(2, "key file %s is readable by others (mode %o); chmod 600 it", path, (unsigned)(sb.st_mode & 0777));
    fd = open(path, O_RDONLY | O_CLOEXEC);
    if (fd < 0) return fail(2, "key file %s: %s", path, strerror(errno));
    n = read(fd, text, sizeof text - 1);
    close(fd);
    if (n < 0) n = 0;
    text[n] = 0;
    while (n && (text[n - 1] == '\n' || text[n - 1] == '\r' || text[n - 1] == ' ')) text[--n] = 0;
    if (n != 64 || strspn(text, "0123456789abcdefABCDEF") != 64)
        return fail(2, "key file %s: expected 64 hex digits (make one with 'rpr-cosim board keygen FILE')", path);
    for (i = 0; i < 32; i++) {
        unsigned v;
        sscanf(text + 2 * i, "%2x", &v);
        key[i] = (uint8_t)v;
    }
    return 0;
}

/* --- status -------------------------------------------------------------------------------- */
static void status_line(FILE *f, const Board *b) {
    int i;
    fprintf(f, "state=%d fault_bits=%d", b->state, b->faults);
    for (i = 0; i < C_COUNT; i++) fprintf(f, " %s=%llu", COUNTER_NAMES[i], (unsigned long long)b->counters[i]);
    fprintf(f, " tick_p50_us=%u tick_p99_us=%u tick_max_us=%lld cpu_per_tick_ns=%u gpio=%s\n", b->p50_us, b->p99_us,
            (long long)(b->late_max_ns / 1000), b->cpu_per_tick_ns, b->gpio_chardev ? "chardev" : "sysfs");
}

static int hexval(int c) { return c >= '0' && c <= '9' ? c - '0' : c >= 'a' && c <= 'f' ? c - 'a' + 10 : -1; }

/* the test harness: see the file comment */
static int step_mode(Board *b) {
    static char line[8192];
    uint8_t d[2048], reply[256];
    while (fgets(line, sizeof line, stdin)) {
        long long t = 0;
        if (line[0] == 'T' && sscanf(line + 1, "%lld", &t) == 1) {
            board_tick(b, t, 0);
            puts("ok");
        } else if (line[0] == 'D') {
            char *p = line + 1, *hex;
            size_t n = 0, r;
            t = strtoll(p, &hex, 10);
            while (*hex == ' ') hex++;
            while (hexval(hex[0]) >= 0 && hexval(hex[1]) >= 0 && n < sizeof d) {
                d[n++] = (uint8_t)(hexval(hex[0]) << 4 | hexval(hex[1]));
                hex += 2;
            }
            r = board_handle(b, d, n, t, reply);
            fputs("R ", stdout);
            if (!r) fputs("-", stdout);
            for (n = 0; n < r; n++) printf("%02x", reply[n]);
            putchar('\n');
        } else if (line[0] == 'S') {
            status_line(stdout, b);
        } else if (line[0] == 'C') {
            break;
        } else {
            puts("?");
        }
        fflush(stdout);
    }
    board_close_outputs(b);
    puts("closed");
    status_line(stdout, b);
    fflush(stdout);
    return 0;
}

/* --- the loop ------------------------------------------------------------------------------ */
/* a tick if one is due: the timerfd's expirations since the last (non-blocking read) */
static void tick_if_due(Board *b, int tfd, int64_t *due, int64_t tick, int64_t *last_tick) {
    uint64_t exp = 0;
    if (read(tfd, &exp, sizeof exp) == sizeof exp && exp > 0) {
        int64_t first = *due, now = now_ns(); /* the oldest expiry not served: missed ticks count */
        *due += (int64_t)exp * tick;
        *last_tick = now;
        board_tick(b, now, now - first);
    }
}

/* the timer's next expiry at `due`, then every `tick` (a new setting drops pending expiries) */
static int arm_timer(int tfd, int64_t due, int64_t tick) {
    struct itimerspec its;
    its.it_value.tv_sec = (time_t)(due / 1000000000ll);
    its.it_value.tv_nsec = (long)(due % 1000000000ll);
    its.it_interval.tv_sec = (time_t)(tick / 1000000000ll);
    its.it_interval.tv_nsec = (long)(tick % 1000000000ll);
    return timerfd_settime(tfd, TFD_TIMER_ABSTIME, &its, NULL);
}

#define BATCH 32

static int serve(Board *b, int sock, double rate, double duration) {
    int64_t tick = (int64_t)llround(1e9 / rate), start = now_ns(), end = duration > 0 ? start + (int64_t)(duration * 1e9) : 0;
    int64_t due = start + tick, last_tick = start;
    struct pollfd pfd[2];
    int tfd = timerfd_create(CLOCK_MONOTONIC, TFD_CLOEXEC | TFD_NONBLOCK);
    static uint8_t d[BATCH][256];
    uint8_t reply[256];
    struct mmsghdr msgs[BATCH];
    struct iovec iov[BATCH];
    struct sockaddr_in from[BATCH];
    b->resample_ns = tick / 2; /* a command within half a tick of the tick's sample uses it */
    if (tfd < 0) return fail(1, "timerfd_create: %s", strerror(errno));
    int filled = 0;
    memset(msgs, 0, sizeof msgs);
    for (filled = 0; filled < BATCH; filled++) {
        iov[filled].iov_base = d[filled];
        iov[filled].iov_len = sizeof d[filled];
        msgs[filled].msg_hdr.msg_iov = &iov[filled];
        msgs[filled].msg_hdr.msg_iovlen = 1;
        msgs[filled].msg_hdr.msg_name = &from[filled];
    }
    if (arm_timer(tfd, due, tick) != 0) return fail(1, "timerfd_settime: %s", strerror(errno));
    board_tick(b, start, 0);
    pfd[0].fd = tfd;
    pfd[0].events = POLLIN;
    pfd[1].fd = sock;
    pfd[1].events = POLLIN;
    while (!g_stop) {
        int64_t now;
        int timeout = -1, k, n;
        if (end) {
            now = now_ns();
            if (now >= end) break;
            timeout = (int)((end - now) / 1000000 + 1);
        }
        if (poll(pfd, 2, timeout) < 0) {
            if (errno == EINTR) continue;
            return fail(1, "poll: %s", strerror(errno));
        }
        if (pfd[0].revents & POLLIN) tick_if_due(b, tfd, &due, tick, &last_tick);
        if (!(pfd[1].revents & POLLIN)) continue;
        /* up to BATCH datagrams in one call (a flood costs one system call per BATCH); larger
         * datagrams than any of the protocol's are truncated, and then malformed.  The kernel
         * writes only the lengths and flags back: those are reset for the entries it filled */
        for (k = 0; k < filled; k++) {
            msgs[k].msg_hdr.msg_namelen = sizeof from[k];
            msgs[k].msg_hdr.msg_flags = 0;
        }
        n = recvmmsg(sock, msgs, BATCH, MSG_DONTWAIT, NULL);
        filled = n > 0 ? n : 0;
        for (k = 0; k < n && !g_stop; k++) {
            size_t r, len = msgs[k].msg_len;
            now = now_ns();
            if (now >= due) tick_if_due(b, tfd, &due, tick, &last_tick); /* a due tick goes first */
            if (msgs[k].msg_hdr.msg_flags & MSG_TRUNC) len = sizeof d[k] + 1;
            now = now_ns();
            r = board_handle(b, d[k], len > sizeof d[k] ? 0 : len, now, reply);
            if (b->last_apply == now) { /* the command did the tick's work: it is this period's tick */
                int64_t late = now - last_tick - tick;
                board_count_tick(b, late > 0 ? late : 0);
                last_tick = now;
                due = now + tick + tick / 2;
                if (arm_timer(tfd, due, tick) != 0) return fail(1, "timerfd_settime: %s", strerror(errno));
            }
            if (r && sendto(sock, reply, r, MSG_DONTWAIT, (struct sockaddr *)&from[k], msgs[k].msg_hdr.msg_namelen) < 0 &&
                g_verbose)
                say("reply to %s:%d failed: %s", inet_ntoa(from[k].sin_addr), ntohs(from[k].sin_port), strerror(errno));
        }
    }
    close(tfd);
    return 0;
}

static int parse_listen(const char *text, struct sockaddr_in *sa) {
    char host[128];
    const char *colon = strrchr(text, ':');
    char *end;
    long port;
    if (!colon || colon == text || (size_t)(colon - text) >= sizeof host) return -1;
    memcpy(host, text, (size_t)(colon - text));
    host[colon - text] = 0;
    port = strtol(colon + 1, &end, 10);
    if (!colon[1] || *end || port < 0 || port > 65535) return -1;
    memset(sa, 0, sizeof *sa);
    sa->sin_family = AF_INET;
    sa->sin_port = htons((uint16_t)port);
    if (strcmp(host, "localhost") == 0) strcpy(host, "127.0.0.1");
    return inet_pton(AF_INET, host, &sa->sin_addr) == 1 ? 0 : -1;
}

static void usage(void) {
    fputs("usage: rpr-board --key FILE [--root /] [--listen 127.0.0.1:5005] [--rate 1000] [--duration S]\n"
          "                 [--rt-priority P] [--gpio auto|sysfs|chardev] [--travel LO,HI] [-v] [--step]\n", stderr);
}

int main(int argc, char **argv) {
    const char *keyfile = NULL, *root = "/", *listen = "127.0.0.1:5005";
    double rate = 1000.0, duration = 0, lo = NAN, hi = NAN;
    int prio = 0, gpio_mode = 0, step = 0, i, rc, sock = -1;
    uint8_t key[32];
    uint32_t first;
    char err[1024];
    struct sockaddr_in sa;
    socklen_t sl = sizeof sa;
    Board *b = &g_board;
    for (i = 1; i < argc; i++) {
        const char *a = argv[i], *v = i + 1 < argc ? argv[i + 1] : NULL;
        int takes = 1;
        if (!strcmp(a, "-v") || !strcmp(a, "--verbose")) { g_verbose = 1; takes = 0; }
        else if (!strcmp(a, "--step")) { step = 1; takes = 0; }
        else if (!strcmp(a, "-h") || !strcmp(a, "--help")) { usage(); return 0; }
        else if (!v) { usage(); return fail(2, "%s needs a value", a); }
        else if (!strcmp(a, "--key")) keyfile = v;
        else if (!strcmp(a, "--root")) root = v;
        else if (!strcmp(a, "--listen")) listen = v;
        else if (!strcmp(a, "--rate")) rate = atof(v);
        else if (!strcmp(a, "--duration")) duration = atof(v);
        else if (!strcmp(a, "--rt-priority")) prio = atoi(v);
        else if (!strcmp(a, "--travel")) { if (sscanf(v, "%lf,%lf", &lo, &hi) != 2 || !(hi > lo)) return fail(2, "--travel %s: expected LO,HI counts with LO < HI", v); }
        else if (!strcmp(a, "--gpio")) {
            if (!strcmp(v, "auto")) gpio_mode = 0;
            else if (!strcmp(v, "sysfs")) gpio_mode = 1;
            else if (!strcmp(v, "chardev")) gpio_mode = 2;
            else return fail(2, "--gpio %s: expected auto, sysfs or chardev", v);
        } else { usage(); return fail(2, "unknown option %s", a); }
        i += takes;
    }
    if (!keyfile) { usage(); return fail(2, "--key FILE is required (make one with 'rpr-cosim board keygen FILE')"); }
    if (!(rate >= 1 && rate <= 20000)) return fail(2, "--rate %g: expected 1..20000 Hz", rate);
    if (prio && (prio < 1 || prio > 99)) return fail(2, "--rt-priority %d: expected 1..99", prio);
    if (!step && parse_listen(listen, &sa) != 0) return fail(2, "--listen %s: expected HOST:PORT with a numeric IPv4 host, e.g. 127.0.0.1:5005", listen);
    if (read_key(keyfile, key) != 0) return 2;
    if (random_bytes((uint8_t *)&first, sizeof first) != 0) return fail(1, "no random bytes (getrandom)");
    board_init(b, key, first);
    b->cpu_now = cpu_ns;
    b->log = log_info;
    if (!isnan(lo)) { b->safety.travel_lo = lo; b->safety.travel_hi = hi; }
    if (io_resolve(b, root, gpio_mode, err, sizeof err) != 0) {
        io_close(b);
        return fail(2, "pins under %s: %s", root, err);
    }
    install_signals();
    if (board_setup_outputs(b) != 0) {
        int e = errno;
        board_close_outputs(b);
        io_close(b);
        return fail(2, "pins under %s: cannot set up the outputs: %s", root, strerror(e));
    }
    if (step) {
        rc = step_mode(b);
        io_close(b);
        return rc;
    }
    sock = socket(AF_INET, SOCK_DGRAM | SOCK_CLOEXEC, 0);
    if (sock < 0 || bind(sock, (struct sockaddr *)&sa, sizeof sa) != 0) {
        int e = errno;
        board_close_outputs(b);
        io_close(b);
        return fail(2, "cannot listen on %s: %s", listen, strerror(e));
    }
    {   /* room for a burst of datagrams ahead of the master's (beyond rmem_max when root) */
        int size = 1 << 19;
        if (setsockopt(sock, SOL_SOCKET, SO_RCVBUFFORCE, &size, sizeof size) != 0)
            setsockopt(sock, SOL_SOCKET, SO_RCVBUF, &size, sizeof size);
    }
    getsockname(sock, (struct sockaddr *)&sa, &sl);
    prctl(PR_SET_TIMERSLACK, 1UL);
    if (prio) {
        struct sched_param sp;
        memset(&sp, 0, sizeof sp);
        sp.sched_priority = prio;
        if (sched_setscheduler(0, SCHED_FIFO, &sp) != 0) {
            int e = errno;
            board_close_outputs(b);
            io_close(b);
            return fail(2, "--rt-priority %d: SCHED_FIFO refused (%s); run as root or drop the option", prio, strerror(e));
        }
        mlockall(MCL_CURRENT | MCL_FUTURE);
    }
    if (strcmp(inet_ntoa(sa.sin_addr), "127.0.0.1") != 0)
        say("listening on %s: reachable from the network (authenticated, not encrypted)", inet_ntoa(sa.sin_addr));
    printf("rpr-board: listening on %s:%d (root %s, %g Hz, GPIO %s%s)\n", inet_ntoa(sa.sin_addr), ntohs(sa.sin_port),
           root, rate, b->gpio_chardev ? "character device" : "sysfs", prio ? ", SCHED_FIFO" : "");
    fflush(stdout);
    rc = serve(b, sock, rate, duration);
    board_close_outputs(b);
    io_close(b);
    close(sock);
    printf("rpr-board: stopped%s%s; outputs zeroed; ", g_stop ? " on " : "", g_stop ? strsignal(g_stop) : "");
    status_line(stdout, b);
    fflush(stdout);
    return rc;
}
