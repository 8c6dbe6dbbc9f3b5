/* setmem-hil reference firmware: the line protocol (C99, no I/O).
 *
 * One command per line (ASCII, '\n' ends it, '\r' ignored), one reply line per command: the
 * value asked for, "OK", or "ERR <why>". Every line the host sends feeds the watchdog.
 * Documented, with the states that refuse each command, in docs/real-time-target.md:
 *
 *   *IDN?                          SETMEM-HIL,reference-target,<version>,fs=<Hz>,delay=<samples>
 *   STATE?                         BYPASS | ENGAGED <gain> | TRIPPED <reason>
 *   LOAD <n>                       start loading n sections (refused while ENGAGED)
 *   SOS <i> <b0> <b1> <b2> <a1> <a2>   section i (0-based) of the LOAD (a0 = 1)
 *   SOSGAIN <g>                    the gain after the sections (refused while ENGAGED)
 *   CHECKSUM?                      CHECKSUM <8 hex digits> (target_core.h), once every section arrived
 *   LIMIT <x> / LIMIT?             the drive limit (> 0; refused while ENGAGED)
 *   ENGAGE <gain>                  0 < gain <= 2; loaded, not TRIPPED; from ENGAGED: a new gain
 *   BYPASS                         compensator out, states zeroed, a trip cleared
 *   INJECT <amplitude> <omega>     the target's own sine at the summing junction (0 0: off)
 *   WATCHDOG <seconds>             bypass (TRIPPED watchdog) when the host is silent that long; 0: off
 *   PING                           OK (feeds the watchdog)
 */
#ifndef SETMEM_TARGET_PROTOCOL_H
#define SETMEM_TARGET_PROTOCOL_H

#include <stddef.h>

#include "target_core.h"

#define SETMEM_FIRMWARE_VERSION "1.1" /* 1.1: the force channel (setmem_target_force_sample, SUMS? F) */
#define SETMEM_PROTOCOL_LINE_MAX 256

/* Handle one command line; the reply (no newline) goes to reply[0..cap). Returns its length. */
size_t setmem_protocol_handle(setmem_target *t, const char *line, char *reply, size_t cap);

#endif /* SETMEM_TARGET_PROTOCOL_H */
