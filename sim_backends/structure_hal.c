/* setmem-hil: a simulated structure behind the firmware's PC port (simulation, not firmware).
 *
 * Linked with firmware/host/hal_host.c built with -DSETMEM_HOST_EXTERNAL_RIG, this file is the
 * rig: hal_read_sensor() returns the structure's response y[k] = C x[k] plus sensor noise and
 * hal_write_drive(u) steps x[k+1] = Ad x[k] + Bd u[k] (the structure discretised for a drive
 * held over each sample, as sim_backends/emulated_target.py does). The structure comes from the
 * text file named by the environment variable SETMEM_HOST_PLANT:
 *
 *     n  noise_rms  seed
 *     Ad (n x n, row by row)  Bd (n)  C (n)
 *
 * The serial-target tests write it from the run's truth and drive this process over a
 * pseudo-terminal, as a board on a serial port.
 */
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>

#include "hal.h"

#define STRUCTURE_MAX_STATES 64

static int loaded;
static size_t nx;
static double Ad[STRUCTURE_MAX_STATES * STRUCTURE_MAX_STATES], Bd[STRUCTURE_MAX_STATES], C[STRUCTURE_MAX_STATES];
static double x[STRUCTURE_MAX_STATES];
static double noise_rms;
static uint64_t rng_state = 88172645463325252ull;

static int read_numbers(FILE *f, double *out, size_t count)
{
    size_t i;
    for (i = 0; i < count; ++i)
        if (fscanf(f, "%lf", &out[i]) != 1)
            return 0;
    return 1;
}

static void load(void)
{
    const char *path = getenv("SETMEM_HOST_PLANT");
    FILE *f = path ? fopen(path, "r") : NULL;
    double head[3];
    loaded = 1;
    if (!f)
        return;
    if (read_numbers(f, head, 3) && head[0] >= 1 && head[0] <= STRUCTURE_MAX_STATES) {
        nx = (size_t)head[0];
        noise_rms = head[1];
        if (head[2] > 0)
            rng_state = (uint64_t)head[2];
        if (!(read_numbers(f, Ad, nx * nx) && read_numbers(f, Bd, nx) && read_numbers(f, C, nx)))
            nx = 0;
    }
    fclose(f);
}

static double uniform(void)
{
    rng_state ^= rng_state << 13;
    rng_state ^= rng_state >> 7;
    rng_state ^= rng_state << 17;
    return ((double)(rng_state >> 11) + 0.5) / 9007199254740992.0;
}

static double gaussian(void)
{
    return sqrt(-2.0 * log(uniform())) * cos(6.283185307179586 * uniform());
}

double hal_read_sensor(void)
{
    double y = 0.0;
    size_t j;
    if (!loaded)
        load();
    for (j = 0; j < nx; ++j)
        y += C[j] * x[j];
    return noise_rms > 0.0 ? y + noise_rms * gaussian() : y;
}

void hal_write_drive(double u)
{
    double next[STRUCTURE_MAX_STATES];
    size_t i, j;
    for (i = 0; i < nx; ++i) {
        double acc = Bd[i] * u;
        for (j = 0; j < nx; ++j)
            acc += Ad[i * nx + j] * x[j];
        next[i] = acc;
    }
    for (i = 0; i < nx; ++i)
        x[i] = next[i];
}
