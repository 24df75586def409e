/* A fake kernel for the GPIO character devices of a fake sysfs tree (tests only), preloaded into
 * the board daemon with LD_PRELOAD.  A regular file .../dev/gpiochipN (first line: the chip's
 * label) stands for the device; open() of it is recorded, and the uAPI v1 ioctls of
 * <linux/gpio.h> on it are answered as the kernel would:
 *
 *   GPIO_GET_CHIPINFO_IOCTL           name, label, 32 lines;
 *   GPIO_GET_LINEHANDLE_IOCTL         writes direction, the default values and the consumer into
 *                                     .../dev/gpiochipN.lines/<offset>/ and returns a handle fd
 *                                     (EBUSY when a line has a consumer already, EINVAL when the
 *                                     line does not exist);
 *   GPIOHANDLE_SET/GET_LINE_VALUES    write / read each line's value file.
 *
 * Closing a handle clears the consumers (a line released); a process killed with SIGKILL leaves
 * the values as they were and the consumer set, as with a real line whose holder died.
 * Everything else goes to the C library.
 */
#define _GNU_SOURCE
#include <dlfcn.h>
#include <errno.h>
#include <fcntl.h>
#include <linux/gpio.h>
#include <stdarg.h>
#include <stdio.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#define API __attribute__((visibility("default")))
#define MAXFD 1024

typedef struct {
    int kind; /* 0 none, 1 chip, 2 line handle */
    char path[512]; /* chip: the chip file; handle: the chip's .lines directory */
    int n;
    unsigned offsets[GPIOHANDLES_MAX];
} Fake;

static Fake fakes[MAXFD];

static int (*real_open)(const char *, int, ...);
static int (*real_ioctl)(int, unsigned long, ...);
static int (*real_close)(int);

static void init(void) {
    if (!real_open) {
        real_open = (int (*)(const char *, int, ...))dlsym(RTLD_NEXT, "open");
        real_ioctl = (int (*)(int, unsigned long, ...))dlsym(RTLD_NEXT, "ioctl");
        real_close = (int (*)(int))dlsym(RTLD_NEXT, "close");
    }
}

static int is_fake_chip(const char *path) {
    const char *base = strrchr(path, '/');
    struct stat sb;
    base = base ? base + 1 : path;
    if (strncmp(base, "gpiochip", 8) != 0 || !base[8] || strspn(base + 8, "0123456789") != strlen(base + 8)) return 0;
    return stat(path, &sb) == 0 && S_ISREG(sb.st_mode);
}

static int put(const char *dir, unsigned off, const char *name, const char *text) {
    char p[700];
    int fd;
    ssize_t n = (ssize_t)strlen(text);
    snprintf(p, sizeof p, "%s/%u/%s", dir, off, name);
    fd = real_open(p, O_WRONLY | O_TRUNC);
    if (fd < 0) return -1;
    if (write(fd, text, (size_t)n) != n) n = -1;
    real_close(fd);
    return n < 0 ? -1 : 0;
}

static int get(const char *dir, unsigned off, const char *name, char *out, size_t cap) {
    char p[700];
    int fd;
    ssize_t n;
    snprintf(p, sizeof p, "%s/%u/%s", dir, off, name);
    fd = real_open(p, O_RDONLY);
    if (fd < 0) return -1;
    n = read(fd, out, cap - 1);
    real_close(fd);
    out[n > 0 ? n : 0] = 0;
    return n < 0 ? -1 : 0;
}

static int do_open(const char *path, int flags, mode_t mode) {
    int fd;
    init();
    fd = real_open(path, flags, mode);
    if (fd >= 0 && fd < MAXFD) {
        fakes[fd].kind = is_fake_chip(path) ? 1 : 0;
        if (fakes[fd].kind) snprintf(fakes[fd].path, sizeof fakes[fd].path, "%s", path);
    }
    return fd;
}

API int open(const char *path, int flags, ...) {
    mode_t mode = 0;
    if (flags & (O_CREAT | O_TMPFILE)) {
        va_list ap;
        va_start(ap, flags);
        mode = (mode_t)va_arg(ap, int);
        va_end(ap);
    }
    return do_open(path, flags, mode);
}

API int open64(const char *path, int flags, ...) {
    mode_t mode = 0;
    if (flags & (O_CREAT | O_TMPFILE)) {
        va_list ap;
        va_start(ap, flags);
        mode = (mode_t)va_arg(ap, int);
        va_end(ap);
    }
    return do_open(path, flags, mode);
}

API int close(int fd) {
    init();
    if (fd >= 0 && fd < MAXFD && fakes[fd].kind == 2) {
        int i;
        for (i = 0; i < fakes[fd].n; i++) put(fakes[fd].path, fakes[fd].offsets[i], "consumer", "");
    }
    if (fd >= 0 && fd < MAXFD) fakes[fd].kind = 0;
    return real_close(fd);
}

static int chip_info(Fake *f, struct gpiochip_info *info) {
    char text[256];
    int fd = real_open(f->path, O_RDONLY);
    ssize_t n;
    const char *base = strrchr(f->path, '/');
    if (fd < 0) return -1;
    n = read(fd, text, sizeof text - 1);
    real_close(fd);
    text[n > 0 ? n : 0] = 0;
    text[strcspn(text, "\n")] = 0;
    memset(info, 0, sizeof *info);
    snprintf(info->name, sizeof info->name, "%s", base ? base + 1 : f->path);
    snprintf(info->label, sizeof info->label, "%s", text);
    info->lines = 32;
    return 0;
}

static int line_handle(Fake *f, struct gpiohandle_request *req) {
    char lines[600], text[64], p[700];
    unsigned i;
    int fd;
    struct stat sb;
    snprintf(lines, sizeof lines, "%s.lines", f->path);
    if (req->lines == 0 || req->lines > GPIOHANDLES_MAX) { errno = EINVAL; return -1; }
    for (i = 0; i < req->lines; i++) {
        snprintf(p, sizeof p, "%s/%u", lines, req->lineoffsets[i]);
        if (stat(p, &sb) != 0 || !S_ISDIR(sb.st_mode)) { errno = EINVAL; return -1; }
        if (get(lines, req->lineoffsets[i], "consumer", text, sizeof text) == 0 && text[0]) { errno = EBUSY; return -1; }
    }
    for (i = 0; i < req->lines; i++) {
        int out = (req->flags & GPIOHANDLE_REQUEST_OUTPUT) != 0;
        put(lines, req->lineoffsets[i], "direction", out ? "out" : "in");
        if (out) put(lines, req->lineoffsets[i], "value", req->default_values[i] ? "1" : "0");
        put(lines, req->lineoffsets[i], "consumer", req->consumer_label[0] ? req->consumer_label : "?");
    }
    fd = real_open(lines, O_RDONLY | O_DIRECTORY | O_CLOEXEC);
    if (fd < 0 || fd >= MAXFD) return -1;
    fakes[fd].kind = 2;
    snprintf(fakes[fd].path, sizeof fakes[fd].path, "%s", lines);
    fakes[fd].n = (int)req->lines;
    memcpy(fakes[fd].offsets, req->lineoffsets, sizeof req->lineoffsets);
    req->fd = fd;
    return 0;
}

API int ioctl(int fd, unsigned long request, ...) {
    va_list ap;
    void *arg;
    Fake *f;
    init();
    va_start(ap, request);
    arg = va_arg(ap, void *);
    va_end(ap);
    if (fd < 0 || fd >= MAXFD || !fakes[fd].kind) return real_ioctl(fd, request, arg);
    f = &fakes[fd];
    if (f->kind == 1 && request == GPIO_GET_CHIPINFO_IOCTL) return chip_info(f, arg);
    if (f->kind == 1 && request == GPIO_GET_LINEHANDLE_IOCTL) return line_handle(f, arg);
    if (f->kind == 2 && request == GPIOHANDLE_SET_LINE_VALUES_IOCTL) {
        struct gpiohandle_data *d = arg;
        int i;
        for (i = 0; i < f->n; i++)
            if (put(f->path, f->offsets[i], "value", d->values[i] ? "1" : "0") != 0) return -1;
        return 0;
    }
    if (f->kind == 2 && request == GPIOHANDLE_GET_LINE_VALUES_IOCTL) {
        struct gpiohandle_data *d = arg;
        char text[8];
        int i;
        memset(d, 0, sizeof *d);
        for (i = 0; i < f->n; i++) {
            if (get(f->path, f->offsets[i], "value", text, sizeof text) != 0) return -1;
            d->values[i] = text[0] == '1';
        }
        return 0;
    }
    errno = ENOTTY;
    return -1;
}
