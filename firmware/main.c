/* setmem-hil reference firmware: the sample interrupt and the serial loop (see hal.h).
 *
 * Build for a board: cc -std=c99 -Wall -Werror -DSETMEM_FS_HZ=2000 -DSETMEM_DELAY_SAMPLES=1 \
 *     main.c target_core.c protocol.c <your hal.c> -lm
 * The interrupt must not run while a command changes the target: a port defines
 * SETMEM_CRITICAL_BEGIN/END (e.g. disable and enable the timer interrupt).
 */
#include "hal.h"
#include "main.h"
#include "protocol.h"
#include "target_core.h"

#ifndef SETMEM_FS_HZ
#define SETMEM_FS_HZ 2000.0
#endif
#ifndef SETMEM_DELAY_SAMPLES
#define SETMEM_DELAY_SAMPLES 1
#endif
#ifndef SETMEM_CRITICAL_BEGIN
#define SETMEM_CRITICAL_BEGIN()
#define SETMEM_CRITICAL_END()
#endif

static setmem_target target;
static char line[SETMEM_PROTOCOL_LINE_MAX];
static unsigned line_length;
static int line_overflow;

void setmem_firmware_init(void)
{
    setmem_target_init(&target, SETMEM_FS_HZ, SETMEM_DELAY_SAMPLES);
    line_length = 0;
    line_overflow = 0;
}

void setmem_firmware_sample(void)
{
    double y = hal_read_sensor();
#ifdef SETMEM_HAL_FORCE
    setmem_target_force_sample(&target, hal_read_force());
#endif
    hal_write_drive(setmem_target_tick(&target, y));
}

static void answer(void)
{
    char reply[SETMEM_PROTOCOL_LINE_MAX + 2];
    size_t n;
    line[line_length] = '\0';
    if (line_overflow) {
        hal_serial("ERR line too long\n");
    } else {
        SETMEM_CRITICAL_BEGIN();
        n = setmem_protocol_handle(&target, line, reply, SETMEM_PROTOCOL_LINE_MAX);
        SETMEM_CRITICAL_END();
        reply[n] = '\n';
        reply[n + 1] = '\0';
        hal_serial(reply);
    }
    line_length = 0;
    line_overflow = 0;
}

int setmem_firmware_poll(void)
{
    int c;
    while ((c = hal_serial(0)) >= 0) {
        if (c == '\r')
            continue;
        if (c == '\n') {
            answer();
            return 1;
        }
        if (line_length + 1 < sizeof line)
            line[line_length++] = (char)c;
        else
            line_overflow = 1;
    }
    return 0;
}
