/* setmem-hil reference firmware: the real-time core (see target_core.h). */
#include "target_core.h"

#include <math.h>
#include <string.h>

void setmem_target_init(setmem_target *t, double fs_hz, unsigned delay_samples)
{
    memset(t, 0, sizeof *t);
    t->fs_hz = fs_hz;
    t->delay_samples = delay_samples > SETMEM_TARGET_MAX_DELAY ? SETMEM_TARGET_MAX_DELAY : delay_samples;
    t->sos_gain = 1.0;
    t->drive_limit = 1.0;
    t->state = SETMEM_BYPASS;
    t->watchdog_ticks = (uint32_t)(0.5 * fs_hz);
}

size_t setmem_target_sizeof(void)
{
    return sizeof(setmem_target);
}

void setmem_target_reset_states(setmem_target *t)
{
    memset(t->w, 0, sizeof t->w);
    memset(t->delay_line, 0, sizeof t->delay_line);
    t->delay_pos = 0;
}

double setmem_target_filter(setmem_target *t, double y)
{
    /* direct form II transposed, as scipy.signal.sosfilt (the gain folded in at the end) */
    double x = y;
    size_t i;
    for (i = 0; i < t->n_sections; ++i) {
        const double *c = t->sos[i];
        double out = c[0] * x + t->w[i][0];
        t->w[i][0] = c[1] * x - c[3] * out + t->w[i][1];
        t->w[i][1] = c[2] * x - c[4] * out;
        x = out;
    }
    return t->sos_gain * x;
}

void setmem_target_feed(setmem_target *t)
{
    t->ticks_since_host = 0;
}

void setmem_target_analyse(setmem_target *t, uint64_t settle, uint64_t count)
{
    memset(&t->analyser, 0, sizeof t->analyser);
    t->analyser.settle_left = settle;
    t->analyser.count = count;
    t->analyser.state = count == 0 ? SETMEM_ANALYSER_DONE : (settle > 0 ? SETMEM_ANALYSER_SETTLING : SETMEM_ANALYSER_SUMMING);
}

/* One sample into the analyser: r, u, y at the injection's sample index n (before it advances). */
static void analyse_sample(setmem_target *t, double r, double u, double y, uint64_t n)
{
    setmem_analyser *a = &t->analyser;
    const double values[4] = {r, u, y, t->has_force ? t->force : 0.0};
    double phase, s, c;
    int i;
    if (a->state == SETMEM_ANALYSER_IDLE || a->state == SETMEM_ANALYSER_DONE)
        return;
    if (fabs(u) > a->peak_drive)
        a->peak_drive = fabs(u);
    if (fabs(y) > a->peak_sensor)
        a->peak_sensor = fabs(y);
    if (a->state == SETMEM_ANALYSER_SETTLING) {
        if (--a->settle_left > 0)
            return;
        a->state = SETMEM_ANALYSER_SUMMING;
        return; /* the next sample is the first summed */
    }
    if (a->done == 0)
        a->first_n = n;
    phase = t->inject_omega_rad_s * (double)n / t->fs_hz;
    s = sin(phase);
    c = cos(phase);
    for (i = 0; i < 4; ++i) {
        a->signal[i][SETMEM_SUM_SIN] += values[i] * s;
        a->signal[i][SETMEM_SUM_COS] += values[i] * c;
        a->signal[i][SETMEM_SUM_PLAIN] += values[i];
        a->signal[i][SETMEM_SUM_SQUARE] += values[i] * values[i];
    }
    a->reference[SETMEM_REF_SS] += s * s;
    a->reference[SETMEM_REF_SC] += s * c;
    a->reference[SETMEM_REF_S] += s;
    a->reference[SETMEM_REF_CC] += c * c;
    a->reference[SETMEM_REF_C] += c;
    if (++a->done == a->count)
        a->state = SETMEM_ANALYSER_DONE;
}

void setmem_target_trip(setmem_target *t, const char *reason)
{
    t->state = SETMEM_TRIPPED;
    t->gain = 0.0;
    t->inject_amplitude = 0.0;
    strncpy(t->reason, reason, SETMEM_TARGET_REASON_LEN - 1);
    t->reason[SETMEM_TARGET_REASON_LEN - 1] = '\0';
    t->last_drive = 0.0;
    t->analyser.state = SETMEM_ANALYSER_IDLE;
}

static double delayed(setmem_target *t, double value)
{
    const unsigned size = SETMEM_TARGET_MAX_DELAY + 1;
    double out;
    t->delay_line[t->delay_pos] = value;
    out = t->delay_line[(t->delay_pos + size - t->delay_samples) % size];
    t->delay_pos = (t->delay_pos + 1) % size;
    return out;
}

void setmem_target_force_sample(setmem_target *t, double f)
{
    t->has_force = 1;
    t->force = f;
}

double setmem_target_tick(setmem_target *t, double y)
{
    double compensator, injection, drive;
    uint64_t n;
    t->ticks++;
    if (t->state == SETMEM_TRIPPED)
        return 0.0;
    if (t->state == SETMEM_ENGAGED && t->watchdog_ticks > 0 && ++t->ticks_since_host > t->watchdog_ticks) {
        setmem_target_trip(t, "watchdog");
        return 0.0;
    }
    /* the filter runs bypassed too, so engaging starts from states that match the structure */
    compensator = setmem_target_filter(t, y);
    compensator = delayed(t, t->state == SETMEM_ENGAGED ? t->gain * compensator : 0.0);
    injection = 0.0;
    n = t->inject_n;
    if (t->inject_amplitude != 0.0)
        injection = t->inject_amplitude * sin(t->inject_omega_rad_s * (double)n / t->fs_hz);
    if (t->inject_omega_rad_s != 0.0) /* the phase runs with the amplitude zero too: the analyser's reference */
        t->inject_n++;
    drive = compensator + injection;
    if (!(fabs(drive) <= t->drive_limit)) { /* NaN trips too */
        setmem_target_trip(t, "drive_limit");
        return 0.0;
    }
    t->last_drive = drive;
    analyse_sample(t, injection, drive, y, n);
    return drive;
}

static uint32_t crc32_update(uint32_t crc, const uint8_t *bytes, size_t n)
{
    size_t i;
    int bit;
    for (i = 0; i < n; ++i) {
        crc ^= bytes[i];
        for (bit = 0; bit < 8; ++bit)
            crc = (crc >> 1) ^ (0xEDB88320u & (0u - (crc & 1u)));
    }
    return crc;
}

static uint32_t crc32_double(uint32_t crc, double value)
{
    uint64_t bits;
    uint8_t bytes[8];
    int i;
    memcpy(&bits, &value, sizeof bits);
    for (i = 0; i < 8; ++i)
        bytes[i] = (uint8_t)(bits >> (8 * i));
    return crc32_update(crc, bytes, 8);
}

uint32_t setmem_target_checksum(const setmem_target *t)
{
    uint32_t crc = 0xFFFFFFFFu;
    uint8_t count[4];
    size_t i;
    int j;
    for (j = 0; j < 4; ++j)
        count[j] = (uint8_t)((uint32_t)t->n_sections >> (8 * j));
    crc = crc32_update(crc, count, 4);
    for (i = 0; i < t->n_sections; ++i)
        for (j = 0; j < 5; ++j)
            crc = crc32_double(crc, t->sos[i][j]);
    crc = crc32_double(crc, t->sos_gain);
    return crc ^ 0xFFFFFFFFu;
}
