/* The reference firmware's line protocol under random and adversarial lines (issue 63 item 3).
 *
 * Built by tests/test_firmware_fuzz.py with -fsanitize=address,undefined,float-cast-overflow and
 * -fno-sanitize-recover=all: any undefined behaviour (a NaN converted to an integer, an overflowing
 * conversion, an out-of-bounds access) aborts the run. Besides the sanitizers it checks, after every
 * line and every sample, the invariants a board must keep whatever the host sends:
 *   - a trip bypasses: TRIPPED drives 0, with the gain and the injection off;
 *   - nothing outside the limit reaches the drive: |drive| <= drive_limit, and never NaN;
 *   - the watchdog cannot be talked out of: engaged with a watchdog on, the host was heard within
 *     it (a sample past it trips), and a watchdog is either off (0) or at least one sample;
 *   - a refused command changes nothing the drive depends on (the state, gain, limit and watchdog);
 *   - every reply is one line within the protocol's 256 characters.
 * Usage: firmware_protocol_fuzz <seed> <lines>; prints one summary line; exit 0 when every check held.
 */
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "protocol.h"
#include "target_core.h"

static uint64_t rng_state;

static uint64_t next(void) /* splitmix64: a fixed sequence per seed, the same on every machine */
{
    uint64_t z = (rng_state += 0x9E3779B97F4A7C15ull);
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    return z ^ (z >> 31);
}

static unsigned pick(unsigned n)
{
    return (unsigned)(next() % n);
}

static const char *const COMMANDS[] = {"*IDN?", "STATE?", "LOAD", "SOS", "SOSGAIN", "CHECKSUM?", "LIMIT", "LIMIT?", "ENGAGE",
                                       "BYPASS", "INJECT", "WATCHDOG", "PING", "ANALYSE", "ANALYSIS?", "SUMS?", "BOGUS", ""};

/* numbers a host, a typo or an attacker might send */
static const char *const ADVERSARIAL[] = {"nan", "NaN", "-nan", "inf", "-inf", "INFINITY", "1e309", "-1e309", "4294967.296",
                                          "4294967296", "1e300", "-1e300", "1e-320", "0", "-0", "0x1p31", "0x7fffffff",
                                          "18446744073709551616", "9.0e15", "9007199254740993", "32", "33", "-1", "1.5",
                                          "2", "2.0000001", "", "abc", "1,5", "+", ".", "e5"};

static void number(char *out, size_t cap)
{
    switch (pick(4)) {
    case 0:
        snprintf(out, cap, "%s", ADVERSARIAL[pick(sizeof ADVERSARIAL / sizeof *ADVERSARIAL)]);
        break;
    case 1:
        snprintf(out, cap, "%u", pick(40));
        break;
    case 2:
        snprintf(out, cap, "%.6g", ((double)pick(2000001) - 1000000.0) / 1000.0);
        break;
    default:
        snprintf(out, cap, "%.3g", pow(10.0, (double)pick(80) - 40.0));
    }
}

static void random_line(char *line, size_t cap)
{
    size_t n;
    unsigned k, count = pick(8);
    char field[64];
    if (pick(50) == 0) { /* an over-long line, or random bytes */
        n = 1 + pick((unsigned)cap - 1);
        for (k = 0; k < n; ++k)
            line[k] = (char)(pick(2) ? 32 + pick(95) : 1 + pick(255));
        line[n] = '\0';
        return;
    }
    n = (size_t)snprintf(line, cap, "%s", COMMANDS[pick(sizeof COMMANDS / sizeof *COMMANDS)]);
    if (pick(3) == 0 && !strcmp(line, "SUMS?"))
        n = (size_t)snprintf(line, cap, "SUMS? %s", pick(2) ? "REF" : (pick(2) ? "R" : (pick(2) ? "F" : "Q")));
    for (k = 0; k < count && n + 1 < cap; ++k) {
        number(field, sizeof field);
        n += (size_t)snprintf(line + n, cap - n, " %s", field);
        if (n >= cap)
            n = cap - 1;
    }
}

struct guarded {
    setmem_state state;
    double gain, drive_limit;
    uint32_t watchdog_ticks;
};

static struct guarded guard_of(const setmem_target *t)
{
    struct guarded g = {t->state, t->gain, t->drive_limit, t->watchdog_ticks};
    return g;
}

static int fail(const char *what, const char *line, uint64_t i)
{
    printf("fuzz: invariant broken at line %llu (%s): %s\n", (unsigned long long)i, line, what);
    return 1;
}

int main(int argc, char **argv)
{
    static setmem_target t;
    char line[SETMEM_PROTOCOL_LINE_MAX + 8], reply[SETMEM_PROTOCOL_LINE_MAX];
    uint64_t lines, i, ticks = 0, refused = 0, engaged = 0, trips = 0;
    if (argc != 3)
        return 2;
    rng_state = strtoull(argv[1], 0, 10);
    lines = strtoull(argv[2], 0, 10);
    setmem_target_init(&t, 2000.0, 3);
    for (i = 0; i < lines; ++i) {
        struct guarded before = guard_of(&t);
        size_t len;
        unsigned k, samples;
        /* a valid session step now and then, so that ENGAGED and the analyser are reached often */
        switch (pick(12)) {
        case 0: snprintf(line, sizeof line, "LOAD 1"); break;
        case 1: snprintf(line, sizeof line, "SOS 0 0.5 0.1 0 -0.2 0.01"); break;
        case 2: snprintf(line, sizeof line, "ENGAGE %.3g", 0.1 + 0.1 * pick(15)); break;
        case 3: snprintf(line, sizeof line, "INJECT %.3g %.3g", 0.01 * pick(50), 0.5 * pick(40)); break;
        case 4: snprintf(line, sizeof line, "ANALYSE %u %u", pick(50), 1 + pick(200)); break;
        default: random_line(line, SETMEM_PROTOCOL_LINE_MAX);
        }
        len = setmem_protocol_handle(&t, line, reply, sizeof reply);
        if (len >= sizeof reply || strlen(reply) != len || strchr(reply, '\n'))
            return fail("a reply longer than the line limit or with a newline", line, i);
        if (!strncmp(reply, "ERR", 3)) {
            struct guarded after = guard_of(&t);
            ++refused;
            if (after.state != before.state || after.gain != before.gain || after.drive_limit != before.drive_limit
                || after.watchdog_ticks != before.watchdog_ticks)
                return fail("a refused command changed the state, gain, limit or watchdog", line, i);
        }
        if (!(t.drive_limit > 0.0) || !isfinite(t.drive_limit))
            return fail("the drive limit is not a finite positive number", line, i);
        if (t.state == SETMEM_ENGAGED && !(t.gain > 0.0 && t.gain <= 2.0))
            return fail("engaged with a gain outside (0, 2]", line, i);
        samples = pick(4) == 0 ? pick(3000) : pick(20);
        for (k = 0; k < samples; ++k) {
            double y = pick(1000) == 0 ? NAN : ((double)pick(2001) - 1000.0) / 500.0;
            double drive;
            if (i > lines / 2) /* the second half: a board with a force channel (any value, NaN too) */
                setmem_target_force_sample(&t, pick(1000) == 0 ? NAN : ((double)pick(2001) - 1000.0) / 100.0);
            drive = setmem_target_tick(&t, y);
            ++ticks;
            if (!(fabs(drive) <= t.drive_limit))
                return fail("a drive outside the limit (or NaN) reached the output", line, i);
            if (t.state == SETMEM_TRIPPED) {
                if (drive != 0.0 || t.gain != 0.0 || t.inject_amplitude != 0.0)
                    return fail("tripped but driving, or with a gain or injection left on", line, i);
            }
            if (t.state == SETMEM_ENGAGED) {
                ++engaged;
                if (t.watchdog_ticks > 0 && t.ticks_since_host > t.watchdog_ticks)
                    return fail("engaged past the watchdog", line, i);
            }
        }
        if (t.state == SETMEM_TRIPPED && before.state != SETMEM_TRIPPED)
            ++trips;
    }
    printf("fuzz: %llu lines (%llu refused), %llu samples (%llu engaged), %llu trips: every invariant held\n",
           (unsigned long long)lines, (unsigned long long)refused, (unsigned long long)ticks, (unsigned long long)engaged,
           (unsigned long long)trips);
    return 0;
}
