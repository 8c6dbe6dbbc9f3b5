/* setmem-hil reference firmware: the port to a PC process (POSIX), for testing the host's driver.
 *
 * The serial line is stdin/stdout (run it behind a pseudo-terminal or a pipe); the sample timer
 * is the wall clock (every 10 ms the samples due are run), sped up by the environment variable
 * SETMEM_HOST_SPEEDUP (a factor, default 1: tests run a structure's minutes in seconds); the
 * sensor reads 0, so the drive is the target's own injection while bypassed. Everything else is
 * the firmware as a board runs it.
 *   cc -std=c99 -Wall -Werror -I.. hal_host.c ../main.c ../target_core.c ../protocol.c -lm
 * With -DSETMEM_HOST_EXTERNAL_RIG the sensor and the drive come from another file (the tests
 * link a simulated structure there: sim_backends/structure_hal.c).
 */
#define _POSIX_C_SOURCE 200809L

#include <stdio.h>
#include <sys/select.h>
#include <time.h>
#include <unistd.h>

#include "../hal.h"
#include "../main.h"

#ifndef SETMEM_FS_HZ
#define SETMEM_FS_HZ 2000.0
#endif

#include <stdlib.h>

#ifndef SETMEM_HOST_EXTERNAL_RIG
double hal_read_sensor(void)
{
    return 0.0;
}

void hal_write_drive(double u)
{
    (void)u;
}
#endif

int hal_serial(const char *text)
{
    fd_set ready;
    struct timeval now = {0, 0};
    unsigned char c;
    if (text) {
        fputs(text, stdout);
        fflush(stdout);
        return 0;
    }
    FD_ZERO(&ready);
    FD_SET(0, &ready);
    if (select(1, &ready, 0, 0, &now) <= 0)
        return -1;
    return read(0, &c, 1) == 1 ? c : -2;
}

static double seconds(void)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (double)t.tv_sec + 1e-9 * (double)t.tv_nsec;
}

int main(void)
{
    const double start = seconds();
    const char *speedup_text = getenv("SETMEM_HOST_SPEEDUP");
    const double speedup = speedup_text && atof(speedup_text) > 0.0 ? atof(speedup_text) : 1.0;
    unsigned long long samples = 0;
    setmem_firmware_init();
    for (;;) {
        fd_set ready;
        struct timeval wait = {0, 10000};
        unsigned long long due;
        FD_ZERO(&ready);
        FD_SET(0, &ready);
        if (select(1, &ready, 0, 0, &wait) > 0 && setmem_firmware_poll() == 0 && hal_serial(0) == -2)
            break; /* the host closed the line */
        due = (unsigned long long)((seconds() - start) * SETMEM_FS_HZ * speedup);
        for (; samples < due; ++samples)
            setmem_firmware_sample();
    }
    return 0;
}
