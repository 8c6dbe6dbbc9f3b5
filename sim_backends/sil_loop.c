/* setmem-hil: software in the loop, the simulation side (not firmware).
 *
 * Steps a sampled structure (x[k+1] = Ad x[k] + Bd u[k]; outputs C x) in closed loop with the
 * reference firmware's core, n samples at once, for sim_backends/emulated_target.py: the same
 * arithmetic as its Python loop (it replaces it for speed), compiled with the firmware's core.
 * Row 0 of C is the response the recorder sees; with `lagged` row 1 is what the target's ADC sees.
 * With `force_channel` the board's second ADC reads the force at the structure's input, sampled
 * with the sensor: the drive held since the previous sample (*held_force carries it across calls),
 * plus its own ADC's noise (force_noise).
 */
#include <stddef.h>
#include <string.h>

#include "target_core.h"

#define SIL_MAX_STATES 128
#define SIL_MAX_PIPELINE 65

/* pipeline: the extra delay's register (length `extra`), rotated in place; returns 0, or -1 when
 * the structure is larger than this harness holds. */
int sil_run(setmem_target *t, size_t n, size_t nx, const double *Ad, const double *Bd, const double *C, int lagged,
            double *x, const double *r, const double *noise, double dac_gain, size_t extra, double *pipeline,
            int force_channel, double *held_force, const double *force_noise, double *u_out, double *y_out)
{
    double next[SIL_MAX_STATES];
    size_t k, i, j;
    if (nx > SIL_MAX_STATES || extra > SIL_MAX_PIPELINE)
        return -1;
    for (k = 0; k < n; ++k) {
        double y = 0.0, seen = 0.0, v, u;
        for (j = 0; j < nx; ++j)
            y += C[j] * x[j];
        if (lagged)
            for (j = 0; j < nx; ++j)
                seen += C[nx + j] * x[j];
        y += noise[k];
        if (force_channel)
            setmem_target_force_sample(t, *held_force + force_noise[k]);
        v = setmem_target_tick(t, lagged ? seen + noise[k] : y);
        if (extra > 0) {
            double oldest = pipeline[0];
            memmove(pipeline, pipeline + 1, (extra - 1) * sizeof *pipeline);
            pipeline[extra - 1] = v;
            v = oldest;
        }
        u = dac_gain * v + r[k];
        for (i = 0; i < nx; ++i) {
            double acc = Bd[i] * u;
            const double *row = Ad + i * nx;
            for (j = 0; j < nx; ++j)
                acc += row[j] * x[j];
            next[i] = acc;
        }
        memcpy(x, next, nx * sizeof *x);
        *held_force = u;
        u_out[k] = u;
        y_out[k] = y;
    }
    return 0;
}
