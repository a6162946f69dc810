/*
 * A stand-in for K-Team's libkhepera, for tests only: tests/test_kh4_driver.py compiles it with
 *     gcc -shared -fPIC -o libkhepera.so libkhepera_stub.c
 * and loads it through onboard.drivers.kh4 exactly as a robot loads the real library.
 *
 * It exports the functions the driver uses, with the prototypes of libkhepera's kb_khepera4.h and
 * knet.h, so wrong ctypes signatures, units or handles show up in the log:
 *
 *   KH4_STUB_LOG          file that gets one line per call: "<function> key=value ...", appended and
 *                         closed at once, so it survives the process being killed.
 *   KH4_STUB_IR           12 raw IR counts in hardware order (8 ring sensors, then 4 ground sensors),
 *                         separated by spaces or commas; missing values are 0.
 *   KH4_STUB_POSITION     "left right" encoder counts returned by kh4_get_position.
 *   KH4_STUB_BATTERY      battery voltage in the DS2781's counts of 9.76 mV (bytes 10-11).
 *   KH4_STUB_FAIL         name of the function that fails (negative code, or NULL for knet_open), or several
 *                         names separated by commas.
 *   KH4_STUB_FAIL_TIMES   if set, how many more calls of those functions fail; the stub counts it down, so
 *                         a glitch of one call is "1" (unset: every call fails).
 *   KH4_STUB_HANG         name(s) of functions that never return (a stuck I2C bus), once the file named by
 *                         KH4_STUB_HANG_AFTER exists (at once if that is unset). Logged before hanging.
 *
 * Every function that takes the dsPic handle logs dev=ok only if it got the very pointer knet_open
 * returned (a 64-bit address: a restype left as int would truncate it), and fails otherwise.
 * Build with -DKH4_STUB_WITHOUT_BATTERY or -DKH4_STUB_WITHOUT_SET_SPEED to leave a symbol out.
 */
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

/* The real knet_dev_t is a larger struct; callers only ever hold a pointer to it. */
typedef struct knet_dev_s {
    unsigned int magic;
} knet_dev_t;

static knet_dev_t the_dspic = {0x4b483444u};

#define STUB_ERROR_NOT_INIT -1  /* what libkhepera returns for a NULL handle */
#define STUB_ERROR_SEND -4      /* KH4_ERROR_FRMSND: the scripted failure */
#define IR_SENSORS 12
#define IR_BUFFER_BYTES (2 * IR_SENSORS)
#define BATTERY_BUFFER_BYTES 12

static void record(const char *format, ...)
{
    const char *path = getenv("KH4_STUB_LOG");
    if (path == NULL) {
        return;
    }
    FILE *log = fopen(path, "a");
    if (log == NULL) {
        return;
    }
    va_list args;
    va_start(args, format);
    vfprintf(log, format, args);
    va_end(args);
    fputc('\n', log);
    fclose(log);
}

static const char *handle_label(const knet_dev_t *dev)
{
    return dev == &the_dspic ? "ok" : "bad";
}

/* Whether `function` is one of the comma-separated names in `list`. */
static int listed(const char *list, const char *function)
{
    size_t length = strlen(function);
    for (const char *name = list;; name++) {
        if (strncmp(name, function, length) == 0 && (name[length] == ',' || name[length] == '\0')) {
            return 1;
        }
        name = strchr(name, ',');
        if (name == NULL) {
            return 0;
        }
    }
}

static int scripted_to_fail(const char *function)
{
    const char *failing = getenv("KH4_STUB_FAIL");
    if (failing == NULL || !listed(failing, function)) {
        return 0;
    }
    const char *times = getenv("KH4_STUB_FAIL_TIMES");
    if (times == NULL) {
        return 1;
    }
    long left = strtol(times, NULL, 10);
    if (left <= 0) {
        return 0;
    }
    char buffer[32];
    snprintf(buffer, sizeof buffer, "%ld", left - 1);
    setenv("KH4_STUB_FAIL_TIMES", buffer, 1);
    return 1;
}

static void hang_if_scripted(const char *function)
{
    const char *hanging = getenv("KH4_STUB_HANG");
    const char *after = getenv("KH4_STUB_HANG_AFTER");
    if (hanging == NULL || !listed(hanging, function)) {
        return;
    }
    FILE *flag = after == NULL ? NULL : fopen(after, "r");
    if (after != NULL && flag == NULL) {
        return;
    }
    if (flag != NULL) {
        fclose(flag);
    }
    record("%s hang=yes", function);
    for (;;) {
        sleep(1);
    }
}

/* 0 for success, or the error code libkhepera would give for a bad handle or the scripted failure. */
static int outcome(const char *function, const knet_dev_t *dev)
{
    hang_if_scripted(function);
    if (dev != &the_dspic) {
        return STUB_ERROR_NOT_INIT;
    }
    return scripted_to_fail(function) ? STUB_ERROR_SEND : 0;
}

/* Parse up to `count` integers from an environment variable; the rest are 0. */
static void scripted_values(const char *variable, long long *values, int count)
{
    const char *text = getenv(variable);
    for (int i = 0; i < count; i++) {
        values[i] = 0;
    }
    for (int i = 0; text != NULL && i < count; i++) {
        char *end = NULL;
        values[i] = strtoll(text, &end, 10);
        if (end == text) {
            break;
        }
        text = end;
        while (*text == ',' || *text == ' ') {
            text++;
        }
    }
}

static void put_uint16_le(char *buffer, int offset, long long value)
{
    buffer[offset] = (char)(value & 0xff);
    buffer[offset + 1] = (char)((value >> 8) & 0xff);
}

int kh4_init(int argc, char *argv[])
{
    record("kh4_init argc=%d argv=%s", argc, argv == NULL ? "null" : "set");
    return scripted_to_fail("kh4_init") ? -1 : 0;
}

knet_dev_t *knet_open(const char *device, int preferred_bus, int argc, char *argv[])
{
    record("knet_open device=%s bus=%d argc=%d argv=%s", device, preferred_bus, argc,
           argv == NULL ? "null" : "set");
    if (scripted_to_fail("knet_open") || strcmp(device, "Khepera4:dsPic") != 0) {
        return NULL;
    }
    return &the_dspic;
}

void knet_close(knet_dev_t *dev)
{
    record("knet_close dev=%s", handle_label(dev));
}

int kh4_SetMode(int regtype, knet_dev_t *hDev)
{
    record("kh4_SetMode mode=%d dev=%s", regtype, handle_label(hDev));
    return outcome("kh4_SetMode", hDev);
}

int kh4_ConfigurePID(char kp, char ki, char kd, knet_dev_t *hDev)
{
    record("kh4_ConfigurePID kp=%d ki=%d kd=%d dev=%s", kp, ki, kd, handle_label(hDev));
    return outcome("kh4_ConfigurePID", hDev);
}

int kh4_SetSpeedProfile(char accinc, char accdiv, char mindacc, char mindec, int max_speed, knet_dev_t *hDev)
{
    record("kh4_SetSpeedProfile acc_inc=%d acc_div=%d min_speed_acc=%d min_speed_dec=%d max_speed=%d dev=%s",
           accinc, accdiv, mindacc, mindec, max_speed, handle_label(hDev));
    return outcome("kh4_SetSpeedProfile", hDev);
}

#ifndef KH4_STUB_WITHOUT_SET_SPEED
int kh4_set_speed(int left, int right, knet_dev_t *hDev)
{
    record("kh4_set_speed left=%d right=%d dev=%s", left, right, handle_label(hDev));
    return outcome("kh4_set_speed", hDev);
}
#endif

int kh4_get_position(int *left, int *right, knet_dev_t *hDev)
{
    long long counts[2];
    record("kh4_get_position dev=%s", handle_label(hDev));
    scripted_values("KH4_STUB_POSITION", counts, 2);
    *left = (int)counts[0];
    *right = (int)counts[1];
    return outcome("kh4_get_position", hDev);
}

int kh4_proximity_ir(char *outbuf, knet_dev_t *hDev)
{
    long long raw[IR_SENSORS];
    record("kh4_proximity_ir dev=%s", handle_label(hDev));
    scripted_values("KH4_STUB_IR", raw, IR_SENSORS);
    for (int i = 0; i < IR_SENSORS; i++) {
        put_uint16_le(outbuf, 2 * i, raw[i]);
    }
    return outcome("kh4_proximity_ir", hDev);
}

#ifndef KH4_STUB_WITHOUT_BATTERY
int kh4_battery_status(char *outbuf, knet_dev_t *hDev)
{
    long long voltage_counts;
    record("kh4_battery_status dev=%s", handle_label(hDev));
    scripted_values("KH4_STUB_BATTERY", &voltage_counts, 1);
    memset(outbuf, 0, BATTERY_BUFFER_BYTES);
    put_uint16_le(outbuf, 10, voltage_counts);
    return outcome("kh4_battery_status", hDev);
}
#endif
