/* setmem-hil reference firmware: the real-time core (C99, no I/O, no allocation).
 *
 * One `setmem_target` holds everything the loop needs between two samples: the compensator's
 * second-order sections (loaded at run time over the line protocol, protocol.c), their states,
 * the engaged gain, the computation delay, the drive limit, the target's own injection and the
 * watchdog. `setmem_target_tick` is called once per sample by the board's timer (main.c); it
 * reads nothing and writes nothing itself: the hardware layer (hal.h) does.
 *
 * The loop (docs/real-time-target.md): positive feedback, u = K y (thesis 6.3.2, footnote 3).
 * The drive written at sample k is
 *
 *     drive[k] = gain * K(y)[k - delay_samples] + r[k]
 *
 * where K(y) runs the sections in direct form II transposed, double precision, exactly as
 * scipy.signal.sosfilt, and r is the target's own injection (a sine at the summing junction;
 * an external generator summed into the drive is the other wiring). A drive beyond the limit
 * trips the target: output zero, state TRIPPED drive_limit, until the host bypasses it.
 */
#ifndef SETMEM_TARGET_CORE_H
#define SETMEM_TARGET_CORE_H

#include <stddef.h>
#include <stdint.h>

#define SETMEM_TARGET_MAX_SECTIONS 32
#define SETMEM_TARGET_MAX_DELAY 64
#define SETMEM_TARGET_REASON_LEN 32

typedef enum {
    SETMEM_ANALYSER_IDLE = 0,
    SETMEM_ANALYSER_SETTLING = 1,
    SETMEM_ANALYSER_SUMMING = 2,
    SETMEM_ANALYSER_DONE = 3
} setmem_analyser_state;

/* The analyser's sums: per signal (r, u, y, f) v*sin, v*cos, v, v*v; then the reference's
 * sin*sin, sin*cos, sin, cos*cos, cos (the phase is the injection's: omega * n / fs). */
enum { SETMEM_SUM_SIN = 0, SETMEM_SUM_COS = 1, SETMEM_SUM_PLAIN = 2, SETMEM_SUM_SQUARE = 3, SETMEM_SIGNAL_SUMS = 4 };
enum { SETMEM_REF_SS = 0, SETMEM_REF_SC = 1, SETMEM_REF_S = 2, SETMEM_REF_CC = 3, SETMEM_REF_C = 4, SETMEM_REF_SUMS = 5 };

typedef struct {
    setmem_analyser_state state;
    uint64_t settle_left, count, done;
    uint64_t first_n; /* the injection's sample index of the first summed sample */
    double signal[4][SETMEM_SIGNAL_SUMS]; /* r, u, y, f (f: the force channel, zero without one) */
    double reference[SETMEM_REF_SUMS];
    double peak_drive, peak_sensor; /* since ANALYSE, settling included */
} setmem_analyser;

typedef enum {
    SETMEM_BYPASS = 0,  /* compensator disconnected: drive = own injection only */
    SETMEM_ENGAGED = 1, /* drive = gain * K(y) delayed + own injection */
    SETMEM_TRIPPED = 2  /* drive = 0 until BYPASS; reason says why */
} setmem_state;

typedef struct {
    /* the compensator: per section b0, b1, b2, a1, a2 (a0 = 1), and the overall gain */
    size_t n_sections;
    double sos[SETMEM_TARGET_MAX_SECTIONS][5];
    double sos_gain;
    double w[SETMEM_TARGET_MAX_SECTIONS][2];
    int loaded; /* 1 once every section of the last LOAD arrived */
    size_t received_count;
    uint8_t received[SETMEM_TARGET_MAX_SECTIONS];

    /* the loop */
    setmem_state state;
    double gain;
    char reason[SETMEM_TARGET_REASON_LEN];
    unsigned delay_samples;
    double delay_line[SETMEM_TARGET_MAX_DELAY + 1];
    unsigned delay_pos;
    double drive_limit;
    double last_drive;

    /* the target's own injection: amplitude * sin(omega * Ts * n); n counts from INJECT */
    double inject_amplitude, inject_omega_rad_s;
    uint64_t inject_n;
    setmem_analyser analyser;

    /* the board's second ADC, when it has one: the force at the structure's input, sampled at the
     * same instant as the sensor (setmem_target_force_sample, before each tick) */
    int has_force;
    double force;

    /* timing and the watchdog: the host must speak every watchdog_ticks samples */
    double fs_hz;
    uint32_t watchdog_ticks, ticks_since_host;
    uint64_t ticks;
} setmem_target;

/* A target at sample rate fs_hz with a computation delay of delay_samples (clamped to
 * SETMEM_TARGET_MAX_DELAY), bypassed, no compensator, drive limit 1, watchdog 0.5 s. */
void setmem_target_init(setmem_target *t, double fs_hz, unsigned delay_samples);

/* One sample: the sensor sample y in, the drive sample out (see the header comment). */
double setmem_target_tick(setmem_target *t, double y);

/* A board with a force channel (a second ADC reading the force transducer at the structure's
 * input) calls this before each setmem_target_tick with that sample: the analyser sums it as
 * signal F (SUMS? F), so the host can tell the actuator's side of the plant from the sensor's.
 * The force does not enter the loop. A board without one never calls it (SUMS? F refused). */
void setmem_target_force_sample(setmem_target *t, double f);

/* The compensator alone, one sample, no delay, gain or limit (what sosfilt computes). */
double setmem_target_filter(setmem_target *t, double y);

/* Zero the sections' states and the delay line. */
void setmem_target_reset_states(setmem_target *t);

/* CRC-32 (IEEE 802.3) of the loaded compensator: the section count as a little-endian uint32,
 * then every coefficient (b0 b1 b2 a1 a2 per section, then sos_gain) as its IEEE-754 binary64
 * bits, little-endian. The host computes the same from what it sent: a coefficient the target
 * parsed differently changes it. */
uint32_t setmem_target_checksum(const setmem_target *t);

/* Start the analyser: wait `settle` samples, then sum `count` samples (see the header comment).
 * Any earlier analysis is dropped. */
void setmem_target_analyse(setmem_target *t, uint64_t settle, uint64_t count);

/* The host spoke: the watchdog starts again. */
void setmem_target_feed(setmem_target *t);

/* Trip: drive zero, state TRIPPED with the reason (truncated). */
void setmem_target_trip(setmem_target *t, const char *reason);

/* sizeof(setmem_target): a host that loads this core as a library allocates it opaquely. */
size_t setmem_target_sizeof(void);

#endif /* SETMEM_TARGET_CORE_H */
