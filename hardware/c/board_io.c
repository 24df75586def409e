/* The daemon's pins under a root directory (see hardware/pins.py for the layout it follows):
 *
 * - PWM: the chip whose sysfs path contains "/<address>.pwm/" (or .ehrpwm/.hrpwm), never by its
 *   pwmchipN number; channel directory pwmM (mainline) or pwm-N:M (BeagleBoard kernels),
 *   exported when absent;
 * - DIR lines: the GPIO character device when the board has one (<root>/dev/gpiochip*: the chip
 *   whose label is the bank's address, "44e07000.gpio", or "gpio-<first>-<last>"), a line
 *   requested as an output at 0 and held by this process; otherwise sysfs gpioK, exported when
 *   absent.  The uAPI ioctls of <linux/gpio.h> are used directly (what libgpiod wraps), so the
 *   binary needs no library on the board;
 * - ADC: the IIO device named TI-am335x-adc*, channel in_voltage<ch>_raw, kept open and read
 *   with pread at offset 0 (sysfs converts again on every read).
 */
#define _GNU_SOURCE
#define _FILE_OFFSET_BITS 64 /* 64-bit directory offsets: a 32-bit board (or qemu-user) reads any file system */
#include <dirent.h>
#include <errno.h>
#include <fcntl.h>
#include <limits.h>
#include <linux/gpio.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/ioctl.h>
#include <sys/random.h>
#include <sys/stat.h>
#include <sys/vfs.h>
#include <time.h>
#include <unistd.h>

#include "board.h"

static const struct { const char *chip; int channel; const char *gpio; int adc; } PINS[LEGS] = BOARD_PINS;
static const char *const BANK_ADDRESS[] = BOARD_GPIO_BANKS;
#define BANKS ((int)(sizeof BANK_ADDRESS / sizeof *BANK_ADDRESS))

int io_write_text(const char *path, const char *text) {
    int fd = open(path, O_WRONLY | O_TRUNC | O_CLOEXEC), rc = 0;
    size_t n = strlen(text);
    if (fd < 0) return -1;
    if (write(fd, text, n) != (ssize_t)n) rc = -1;
    if (close(fd) != 0) rc = -1;
    return rc;
}

int io_write_int(const char *path, long v) {
    char buf[32];
    snprintf(buf, sizeof buf, "%ld", v);
    return io_write_text(path, buf);
}

long io_read_int(const char *path, int *ok) {
    char buf[64];
    int fd = open(path, O_RDONLY | O_CLOEXEC);
    ssize_t n;
    char *end;
    long v;
    *ok = 0;
    if (fd < 0) return 0;
    n = read(fd, buf, sizeof buf - 1);
    close(fd);
    if (n <= 0) return 0;
    buf[n] = 0;
    v = strtol(buf, &end, 10);
    if (end == buf) return 0;
    *ok = 1;
    return v;
}

/* An output attribute opened once and written with pwrite at offset 0: the tick's writes cost
 * one system call and no path lookup.  sysfs takes every such write as a new value.  A regular
 * file (a fake tree) is rewritten in place, padded with spaces to its old length and then cut
 * to the new one, so a reader sees a whole number at every moment (int() ignores the spaces). */
#define SYSFS_MAGIC_NUMBER 0x62656572
int io_open_out(OutFile *o, const char *path) {
    struct statfs fs;
    struct stat st;
    o->fd = open(path, O_WRONLY | O_CLOEXEC);
    if (o->fd < 0) return -1;
    o->sysfs = fstatfs(o->fd, &fs) == 0 && (unsigned long)fs.f_type == SYSFS_MAGIC_NUMBER;
    o->len = fstat(o->fd, &st) == 0 && st.st_size < 64 ? (int)st.st_size : 0;
    return 0;
}

int io_put_int(OutFile *o, long v) {
    char buf[80];
    int n = snprintf(buf, 64, "%ld", v), w = n;
    if (o->fd < 0) return -1;
    if (!o->sysfs && o->len > n) {
        memset(buf + n, ' ', (size_t)(o->len - n));
        w = o->len;
    }
    if (pwrite(o->fd, buf, (size_t)w, 0) != (ssize_t)w) return -1;
    if (!o->sysfs && w > n && ftruncate(o->fd, n) != 0) return -1;
    o->len = n;
    return 0;
}

int io_read_adc(Leg *leg, int *raw) {
    char buf[24], *end;
    ssize_t n = pread(leg->adc_fd, buf, sizeof buf - 1, 0);
    long v;
    if (n <= 0) return -1;
    buf[n] = 0;
    v = strtol(buf, &end, 10);
    if (end == buf || (*end && *end != '\n' && *end != ' ')) return -1;
    *raw = (int)v;
    return 0;
}

int io_set_dir(Leg *leg, int high) {
    if (leg->line_fd >= 0) {
        struct gpiohandle_data data;
        memset(&data, 0, sizeof data);
        data.values[0] = (uint8_t)(high != 0);
        return ioctl(leg->line_fd, GPIOHANDLE_SET_LINE_VALUES_IOCTL, &data) < 0 ? -1 : 0;
    }
    return io_put_int(&leg->dir_out, high != 0);
}

static int is_dir(const char *p) {
    struct stat sb;
    return stat(p, &sb) == 0 && S_ISDIR(sb.st_mode);
}

static int wait_dir(const char *a, const char *b) {
    int k;
    for (k = 0; k < 100; k++) { /* up to 1 s for udev to make the exported directory */
        struct timespec ts = {0, 10000000};
        if (is_dir(a) || (b && is_dir(b))) return 0;
        nanosleep(&ts, NULL);
    }
    return -1;
}

static int by_name(const struct dirent **a, const struct dirent **b) { return strcmp((*a)->d_name, (*b)->d_name); }

static int find_pwm_chip(const char *root, const char *address, char *out, char *err, size_t errlen) {
    char dir[PATHLEN], entry[PATHLEN * 2], real[PATH_MAX], pat[3][64];
    struct dirent **names;
    int n, i, found = 0;
    snprintf(dir, sizeof dir, "%s/sys/class/pwm", root);
    n = scandir(dir, &names, NULL, by_name);
    if (n < 0) {
        snprintf(err, errlen, "no PWM class directory %s (is the PWM overlay loaded?)", dir);
        return -1;
    }
    snprintf(pat[0], sizeof pat[0], "/%s.pwm/", address);
    snprintf(pat[1], sizeof pat[1], "/%s.ehrpwm/", address);
    snprintf(pat[2], sizeof pat[2], "/%s.hrpwm/", address);
    for (i = 0; i < n; i++) {
        if (!found && strncmp(names[i]->d_name, "pwmchip", 7) == 0) {
            snprintf(entry, sizeof entry, "%s/%s", dir, names[i]->d_name);
            if (realpath(entry, real)) {
                size_t l = strlen(real);
                if (l + 1 < sizeof real) { real[l] = '/'; real[l + 1] = 0; }
                if (strstr(real, pat[0]) || strstr(real, pat[1]) || strstr(real, pat[2])) {
                    real[l] = 0;
                    snprintf(out, PATHLEN, "%s", real);
                    found = 1;
                }
            }
        }
        free(names[i]);
    }
    free(names);
    if (!found) snprintf(err, errlen, "no PWM chip at address %s under %s", address, dir);
    return found ? 0 : -1;
}

static int pwm_channel(const char *chip, int channel, char *out, char *err, size_t errlen) {
    char a[PATHLEN + 16], b[PATHLEN + 32], exp[PATHLEN + 16], num[16];
    const char *base = strrchr(chip, '/');
    const char *n = base && strncmp(base + 1, "pwmchip", 7) == 0 ? base + 8 : "";
    snprintf(a, sizeof a, "%s/pwm%d", chip, channel);
    snprintf(b, sizeof b, "%s/pwm-%s:%d", chip, n, channel);
    if (!is_dir(a) && !is_dir(b)) {
        snprintf(exp, sizeof exp, "%s/export", chip);
        snprintf(num, sizeof num, "%d", channel);
        if (io_write_text(exp, num) != 0) {
            snprintf(err, errlen, "cannot write %d to %s: %s", channel, exp, strerror(errno));
            return -1;
        }
        if (wait_dir(a, b) != 0) {
            snprintf(err, errlen, "exporting PWM channel %d of %s made no pwm%d or pwm-%s:%d", channel, chip, channel, n,
                     channel);
            return -1;
        }
    }
    snprintf(out, PATHLEN, "%s", is_dir(a) ? a : b);
    return 0;
}

static int gpio_number(const char *label) {
    int bank, idx;
    char tail;
    if (sscanf(label, "gpio%d_%d%c", &bank, &idx, &tail) == 2 && idx >= 0 && idx < 32 && bank >= 0) return bank * 32 + idx;
    if (sscanf(label, "%d%c", &idx, &tail) == 1 && idx >= 0) return idx;
    return -1;
}

static int gpio_sysfs(const char *root, int k, Leg *leg, char *err, size_t errlen) {
    char d[PATHLEN], exp[PATHLEN], num[16];
    snprintf(d, sizeof d, "%s/sys/class/gpio/gpio%d", root, k);
    if (!is_dir(d)) {
        snprintf(exp, sizeof exp, "%s/sys/class/gpio/export", root);
        snprintf(num, sizeof num, "%d", k);
        if (io_write_text(exp, num) != 0) {
            snprintf(err, errlen, "cannot write %d to %s: %s", k, exp, strerror(errno));
            return -1;
        }
        if (wait_dir(d, NULL) != 0) {
            snprintf(err, errlen, "exporting GPIO %d made no %s", k, d);
            return -1;
        }
    }
    snprintf(leg->dir_value, PATHLEN, "%s/value", d);
    snprintf(leg->dir_direction, PATHLEN, "%s/direction", d);
    leg->line_fd = -1;
    return 0;
}

static int has_chardev(const char *root) {
    char dir[PATHLEN];
    struct dirent **names;
    int n, i, found = 0;
    snprintf(dir, sizeof dir, "%s/dev", root);
    n = scandir(dir, &names, NULL, by_name);
    for (i = 0; i < n; i++) {
        size_t l = strlen(names[i]->d_name);
        if (strncmp(names[i]->d_name, "gpiochip", 8) == 0 && l > 8 && strspn(names[i]->d_name + 8, "0123456789") == l - 8)
            found = 1;
        free(names[i]);
    }
    if (n >= 0) free(names);
    return found;
}

static int gpio_chardev(const char *root, int k, Leg *leg, char *err, size_t errlen) {
    char dir[PATHLEN], path[PATHLEN * 2], want[32];
    struct dirent **names;
    int n, i, bank = k / 32, line = k % 32, chip_fd = -1;
    if (bank >= BANKS) {
        snprintf(err, errlen, "GPIO %d: the SoC has banks 0..%d", k, BANKS - 1);
        return -1;
    }
    snprintf(want, sizeof want, "gpio-%d-%d", bank * 32, bank * 32 + 31);
    snprintf(dir, sizeof dir, "%s/dev", root);
    n = scandir(dir, &names, NULL, by_name);
    for (i = 0; i < n; i++) {
        if (chip_fd < 0 && strncmp(names[i]->d_name, "gpiochip", 8) == 0) {
            struct gpiochip_info info;
            int fd;
            snprintf(path, sizeof path, "%s/%s", dir, names[i]->d_name);
            fd = open(path, O_RDWR | O_CLOEXEC);
            memset(&info, 0, sizeof info);
            if (fd >= 0 && ioctl(fd, GPIO_GET_CHIPINFO_IOCTL, &info) == 0 &&
                (strcmp(info.label, want) == 0 || strstr(info.label, BANK_ADDRESS[bank]) != NULL))
                chip_fd = fd;
            else if (fd >= 0)
                close(fd);
        }
        free(names[i]);
    }
    if (n >= 0) free(names);
    if (chip_fd < 0) {
        snprintf(err, errlen, "no GPIO chip labelled %s or %s.gpio under %s", want, BANK_ADDRESS[bank], dir);
        return -1;
    }
    {
        struct gpiohandle_request req;
        memset(&req, 0, sizeof req);
        req.lineoffsets[0] = (uint32_t)line;
        req.lines = 1;
        req.flags = GPIOHANDLE_REQUEST_OUTPUT;
        req.default_values[0] = 0;
        snprintf(req.consumer_label, sizeof req.consumer_label, "rpr-board");
        if (ioctl(chip_fd, GPIO_GET_LINEHANDLE_IOCTL, &req) < 0) {
            snprintf(err, errlen, "GPIO %d (bank %d line %d): cannot request it as an output: %s", k, bank, line,
                     strerror(errno));
            close(chip_fd);
            return -1;
        }
        close(chip_fd);
        leg->line_fd = req.fd;
    }
    snprintf(leg->dir_value, PATHLEN, "gpiochip line %d:%d", bank, line);
    leg->dir_direction[0] = 0;
    return 0;
}

static int find_adc(const char *root, char *out, char *err, size_t errlen) {
    char dir[PATHLEN], name[PATHLEN * 2], text[64];
    struct dirent **names;
    int n, i, found = 0;
    snprintf(dir, sizeof dir, "%s/sys/bus/iio/devices", root);
    n = scandir(dir, &names, NULL, by_name);
    for (i = 0; i < n; i++) {
        if (!found && strncmp(names[i]->d_name, "iio:device", 10) == 0) {
            int fd;
            ssize_t r;
            snprintf(name, sizeof name, "%s/%s/name", dir, names[i]->d_name);
            fd = open(name, O_RDONLY | O_CLOEXEC);
            r = fd >= 0 ? read(fd, text, sizeof text - 1) : -1;
            if (fd >= 0) close(fd);
            if (r > 0) {
                text[r] = 0;
                if (strncmp(text, BOARD_ADC_PREFIX, strlen(BOARD_ADC_PREFIX)) == 0) {
                    snprintf(out, PATHLEN, "%s/%s", dir, names[i]->d_name);
                    found = 1;
                }
            }
        }
        free(names[i]);
    }
    if (n >= 0) free(names);
    if (!found) snprintf(err, errlen, "no IIO device named %s* under %s (is the ADC overlay loaded?)", BOARD_ADC_PREFIX, dir);
    return found ? 0 : -1;
}

int io_resolve(Board *b, const char *root, int gpio_mode, char *err, size_t errlen) {
    char adc[PATHLEN], chip[PATHLEN], ch[PATHLEN];
    int i;
    if (strlen(root) > PATHLEN - 200) {
        snprintf(err, errlen, "the root path is longer than %d characters", PATHLEN - 200);
        return -1;
    }
    if (find_adc(root, adc, err, errlen) != 0) return -1;
    if (gpio_mode == 0) gpio_mode = has_chardev(root) ? 2 : 1;
    b->gpio_chardev = gpio_mode == 2;
    for (i = 0; i < LEGS; i++) {
        Leg *leg = &b->legs[i];
        char e[PATHLEN + 64];
        int k = gpio_number(PINS[i].gpio);
        if (find_pwm_chip(root, PINS[i].chip, chip, err, errlen) != 0) return -1;
        if (pwm_channel(chip, PINS[i].channel, ch, err, errlen) != 0) return -1;
        snprintf(leg->duty, PATHLEN, "%.*s/duty_cycle", PATHLEN - 12, ch);
        snprintf(leg->period, PATHLEN, "%.*s/period", PATHLEN - 8, ch);
        snprintf(leg->enable, PATHLEN, "%.*s/enable", PATHLEN - 8, ch);
        if (k < 0) {
            snprintf(err, errlen, "leg %d: GPIO line %s: expected a number (60) or a label (gpio1_28)", i + 1, PINS[i].gpio);
            return -1;
        }
        if ((gpio_mode == 2 ? gpio_chardev : gpio_sysfs)(root, k, leg, err, errlen) != 0) return -1;
        snprintf(e, sizeof e, "%s/in_voltage%d_raw", adc, PINS[i].adc);
        snprintf(leg->adc, PATHLEN, "%.*s", PATHLEN - 1, e);
        if (io_open_out(&leg->duty_out, leg->duty) != 0) {
            snprintf(err, errlen, "leg %d: PWM duty file %s: %s", i + 1, leg->duty, strerror(errno));
            return -1;
        }
        if (leg->line_fd < 0 && io_open_out(&leg->dir_out, leg->dir_value) != 0) {
            snprintf(err, errlen, "leg %d: GPIO value file %s: %s", i + 1, leg->dir_value, strerror(errno));
            return -1;
        }
        leg->adc_fd = open(leg->adc, O_RDONLY | O_CLOEXEC);
        if (leg->adc_fd < 0) {
            snprintf(err, errlen, "leg %d: ADC channel file %s: %s", i + 1, leg->adc, strerror(errno));
            return -1;
        }
    }
    return 0;
}

void io_close(Board *b) {
    int i;
    for (i = 0; i < LEGS; i++) {
        if (b->legs[i].adc_fd >= 0) close(b->legs[i].adc_fd);
        if (b->legs[i].line_fd >= 0) close(b->legs[i].line_fd);
        if (b->legs[i].duty_out.fd >= 0) close(b->legs[i].duty_out.fd);
        if (b->legs[i].dir_out.fd >= 0) close(b->legs[i].dir_out.fd);
        b->legs[i].adc_fd = b->legs[i].line_fd = b->legs[i].duty_out.fd = b->legs[i].dir_out.fd = -1;
    }
}

/* The kernel's random bytes (a session's challenge, the first sequence number); 0 or -1. */
int random_bytes(uint8_t *out, size_t n) {
    size_t got = 0;
    while (got < n) {
        ssize_t k = getrandom(out + got, n - got, 0);
        if (k < 0 && errno == EINTR) continue;
        if (k <= 0) return -1;
        got += (size_t)k;
    }
    return 0;
}
