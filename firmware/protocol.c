/* setmem-hil reference firmware: the line protocol (see protocol.h). */
#include "protocol.h"

#include <ctype.h>
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* The length snprintf wrote (it returns what it would have written, or < 0 on error). */
static size_t fitted(int n, size_t cap)
{
    return n < 0 ? 0 : ((size_t)n < cap ? (size_t)n : cap - 1);
}

static size_t say(char *reply, size_t cap, const char *text)
{
    return fitted(snprintf(reply, cap, "%s", text), cap);
}

/* Parse exactly `count` finite numbers from `args`; 0 when a field is missing, malformed, extra or
 * not finite. strtod reads "nan", "inf" and overflows ("1e999") as numbers: every command refuses
 * them here, before any range check or conversion to an integer (a NaN converted to size_t or an
 * out-of-range double to uint32_t is undefined behaviour; found with -fsanitize=float-cast-overflow). */
static int numbers(const char *args, double *out, int count)
{
    const char *p = args;
    char *end;
    int i;
    for (i = 0; i < count; ++i) {
        out[i] = strtod(p, &end);
        if (end == p || !isfinite(out[i]))
            return 0;
        p = end;
    }
    while (isspace((unsigned char)*p))
        ++p;
    return *p == '\0';
}

static int is_engaged(const setmem_target *t)
{
    return t->state == SETMEM_ENGAGED;
}

static size_t load(setmem_target *t, const char *args, char *reply, size_t cap)
{
    double n;
    if (is_engaged(t))
        return say(reply, cap, "ERR engaged: BYPASS before LOAD");
    if (!numbers(args, &n, 1) || n < 1 || n > SETMEM_TARGET_MAX_SECTIONS || n != (double)(size_t)n)
        return say(reply, cap, "ERR LOAD needs a section count from 1 to 32");
    t->n_sections = (size_t)n;
    t->received_count = 0;
    t->loaded = 0;
    t->sos_gain = 1.0;
    memset(t->received, 0, sizeof t->received);
    memset(t->sos, 0, sizeof t->sos);
    setmem_target_reset_states(t);
    return say(reply, cap, "OK");
}

static size_t section(setmem_target *t, const char *args, char *reply, size_t cap)
{
    double v[6];
    size_t i;
    int j;
    if (is_engaged(t))
        return say(reply, cap, "ERR engaged: BYPASS before SOS");
    if (!numbers(args, v, 6))
        return say(reply, cap, "ERR SOS needs an index and five coefficients b0 b1 b2 a1 a2");
    if (t->n_sections == 0 || v[0] < 0 || v[0] >= (double)t->n_sections || v[0] != (double)(size_t)v[0])
        return say(reply, cap, "ERR SOS index outside the LOAD");
    i = (size_t)v[0];
    for (j = 0; j < 5; ++j)
        t->sos[i][j] = v[j + 1];
    if (!t->received[i]) {
        t->received[i] = 1;
        t->received_count++;
    }
    t->loaded = t->received_count == t->n_sections;
    setmem_target_reset_states(t);
    return say(reply, cap, "OK");
}

static size_t engage(setmem_target *t, const char *args, char *reply, size_t cap)
{
    double gain;
    if (t->state == SETMEM_TRIPPED)
        return say(reply, cap, "ERR tripped: BYPASS to clear the trip first");
    if (!t->loaded)
        return say(reply, cap, "ERR no compensator loaded");
    if (!numbers(args, &gain, 1) || !(gain > 0.0 && gain <= 2.0))
        return say(reply, cap, "ERR ENGAGE needs a gain in (0, 2]");
    t->gain = gain;
    t->state = SETMEM_ENGAGED;
    return say(reply, cap, "OK");
}

static size_t state(const setmem_target *t, char *reply, size_t cap)
{
    int n;
    if (t->state == SETMEM_ENGAGED)
        n = snprintf(reply, cap, "ENGAGED %.17g", t->gain);
    else if (t->state == SETMEM_TRIPPED)
        n = snprintf(reply, cap, "TRIPPED %s", t->reason);
    else
        n = snprintf(reply, cap, "BYPASS");
    return fitted(n, cap);
}

static size_t settings(setmem_target *t, const char *command, const char *args, char *reply, size_t cap)
{
    double v[2];
    int n;
    if (strcmp(command, "LIMIT?") == 0) {
        return fitted(snprintf(reply, cap, "%.17g", t->drive_limit), cap);
    }
    if (strcmp(command, "LIMIT") == 0) {
        if (is_engaged(t))
            return say(reply, cap, "ERR engaged: BYPASS before LIMIT");
        if (!numbers(args, v, 1) || !(v[0] > 0.0))
            return say(reply, cap, "ERR LIMIT needs a positive drive limit");
        t->drive_limit = v[0];
        return say(reply, cap, "OK");
    }
    if (strcmp(command, "SOSGAIN") == 0) {
        if (is_engaged(t))
            return say(reply, cap, "ERR engaged: BYPASS before SOSGAIN");
        if (!numbers(args, v, 1))
            return say(reply, cap, "ERR SOSGAIN needs a number");
        t->sos_gain = v[0];
        return say(reply, cap, "OK");
    }
    if (strcmp(command, "INJECT") == 0) {
        if (t->state == SETMEM_TRIPPED)
            return say(reply, cap, "ERR tripped: BYPASS to clear the trip first");
        if (!numbers(args, v, 2) || !(v[0] >= 0.0) || !(v[1] >= 0.0))
            return say(reply, cap, "ERR INJECT needs an amplitude >= 0 and a frequency >= 0 rad/s");
        t->inject_amplitude = v[0];
        t->inject_omega_rad_s = v[1];
        t->inject_n = 0;
        t->analyser.state = SETMEM_ANALYSER_IDLE; /* sums of another injection mean nothing */
        return say(reply, cap, "OK");
    }
    if (strcmp(command, "WATCHDOG") == 0) {
        /* the ticks are a uint32_t: at most UINT32_MAX samples (about 24 days at 2 kHz); a longer
         * watchdog is refused, never wrapped to a short one or (UB) to anything at all */
        const double longest = (double)UINT32_MAX / t->fs_hz;
        if (!numbers(args, v, 1) || !(v[0] >= 0.0) || !(v[0] <= longest)) {
            n = snprintf(reply, cap, "ERR WATCHDOG needs seconds from 0 (off) to %.17g", longest);
            return fitted(n, cap);
        }
        if (v[0] > 0.0 && v[0] * t->fs_hz < 1.0)
            return say(reply, cap, "ERR WATCHDOG shorter than one sample: 0 turns it off");
        t->watchdog_ticks = (uint32_t)(v[0] * t->fs_hz);
        t->ticks_since_host = 0;
        return say(reply, cap, "OK");
    }
    n = snprintf(reply, cap, "ERR unknown command %.40s", command);
    return fitted(n, cap);
}

static int whole(double v)
{
    return v >= 0.0 && v <= 9.0e15 && v == (double)(uint64_t)v;
}

static size_t analyse(setmem_target *t, const char *args, char *reply, size_t cap)
{
    double v[2];
    if (t->state == SETMEM_TRIPPED)
        return say(reply, cap, "ERR tripped: BYPASS to clear the trip first");
    if (!numbers(args, v, 2) || !whole(v[0]) || !whole(v[1]) || v[1] < 1.0)
        return say(reply, cap, "ERR ANALYSE needs whole numbers of samples: settle >= 0 and count >= 1");
    if (!(t->inject_omega_rad_s > 0.0))
        return say(reply, cap, "ERR ANALYSE needs an injection frequency: INJECT first (amplitude 0 for the rig at rest)");
    setmem_target_analyse(t, (uint64_t)v[0], (uint64_t)v[1]);
    return say(reply, cap, "OK");
}

static size_t analysis(const setmem_target *t, char *reply, size_t cap)
{
    const setmem_analyser *a = &t->analyser;
    int n;
    switch (a->state) {
    case SETMEM_ANALYSER_SETTLING:
        n = snprintf(reply, cap, "SETTLING %llu %.17g %.17g", (unsigned long long)a->settle_left, a->peak_drive, a->peak_sensor);
        break;
    case SETMEM_ANALYSER_SUMMING:
        n = snprintf(reply, cap, "SUMMING %llu %llu %.17g %.17g", (unsigned long long)a->done, (unsigned long long)a->count,
                     a->peak_drive, a->peak_sensor);
        break;
    case SETMEM_ANALYSER_DONE:
        n = snprintf(reply, cap, "DONE %llu %llu %.17g %.17g", (unsigned long long)a->first_n, (unsigned long long)a->count,
                     a->peak_drive, a->peak_sensor);
        break;
    default:
        n = snprintf(reply, cap, "IDLE");
    }
    return fitted(n, cap);
}

static size_t sums(const setmem_target *t, const char *args, char *reply, size_t cap)
{
    const char *names = "RUYF";
    const double *v;
    while (isspace((unsigned char)*args))
        ++args;
    if (t->analyser.state != SETMEM_ANALYSER_DONE)
        return say(reply, cap, "ERR no analysis done: ANALYSE, then wait for ANALYSIS? DONE");
    if (strncmp(args, "REF", 3) == 0) {
        v = t->analyser.reference;
        return fitted(snprintf(reply, cap, "%.17g %.17g %.17g %.17g %.17g", v[0], v[1], v[2], v[3], v[4]), cap);
    }
    if (args[0] == '\0' || args[1] != '\0' || strchr(names, toupper((unsigned char)args[0])) == 0)
        return say(reply, cap, "ERR SUMS? needs R, U, Y, F or REF");
    if (toupper((unsigned char)args[0]) == 'F' && !t->has_force)
        return say(reply, cap, "ERR no force channel on this board");
    v = t->analyser.signal[strchr(names, toupper((unsigned char)args[0])) - names];
    return fitted(snprintf(reply, cap, "%.17g %.17g %.17g %.17g", v[0], v[1], v[2], v[3]), cap);
}

size_t setmem_protocol_handle(setmem_target *t, const char *line, char *reply, size_t cap)
{
    char command[16];
    size_t n = 0;
    int written;
    setmem_target_feed(t);
    while (isspace((unsigned char)*line))
        ++line;
    while (*line && !isspace((unsigned char)*line) && n + 1 < sizeof command)
        command[n++] = (char)toupper((unsigned char)*line++);
    command[n] = '\0';
    if (strcmp(command, "*IDN?") == 0) {
        written = snprintf(reply, cap, "SETMEM-HIL,reference-target,%s,fs=%.17g,delay=%u", SETMEM_FIRMWARE_VERSION, t->fs_hz,
                           t->delay_samples);
        return fitted(written, cap);
    }
    if (strcmp(command, "STATE?") == 0)
        return state(t, reply, cap);
    if (strcmp(command, "PING") == 0)
        return say(reply, cap, "OK");
    if (strcmp(command, "BYPASS") == 0) {
        t->state = SETMEM_BYPASS;
        t->gain = 0.0;
        t->reason[0] = '\0';
        setmem_target_reset_states(t);
        return say(reply, cap, "OK");
    }
    if (strcmp(command, "LOAD") == 0)
        return load(t, line, reply, cap);
    if (strcmp(command, "SOS") == 0)
        return section(t, line, reply, cap);
    if (strcmp(command, "CHECKSUM?") == 0) {
        if (!t->loaded)
            return say(reply, cap, "ERR not loaded: LOAD and every SOS first");
        written = snprintf(reply, cap, "CHECKSUM %08lX", (unsigned long)setmem_target_checksum(t));
        return fitted(written, cap);
    }
    if (strcmp(command, "ENGAGE") == 0)
        return engage(t, line, reply, cap);
    if (strcmp(command, "ANALYSE") == 0)
        return analyse(t, line, reply, cap);
    if (strcmp(command, "ANALYSIS?") == 0)
        return analysis(t, reply, cap);
    if (strcmp(command, "SUMS?") == 0)
        return sums(t, line, reply, cap);
    return settings(t, command, line, reply, cap);
}
