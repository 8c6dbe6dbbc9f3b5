/* setmem-hil reference firmware: the hardware layer a board port provides (three functions; a
 * fourth, hal_read_force, with -DSETMEM_HAL_FORCE).
 *
 * A port implements these for its ADC, DAC and UART and calls setmem_firmware_sample() from a
 * timer interrupt at SETMEM_FS_HZ and setmem_firmware_poll() from its main loop (main.c).
 * firmware/host/hal_host.c is the port to a PC process (stdin/stdout as the serial line), used to
 * test the host's driver against this firmware.
 */
#ifndef SETMEM_TARGET_HAL_H
#define SETMEM_TARGET_HAL_H

/* The sensor sample (the structure's response y), in the units the compensator was designed in. */
double hal_read_sensor(void);

#ifdef SETMEM_HAL_FORCE
/* Only for a port built with -DSETMEM_HAL_FORCE (a board with a second ADC on the force transducer
 * at the structure's input, sampled at the same instant as the sensor): the force sample, in the
 * drive's units (1 per unit of drive through a nominal amplifier). The analyser sums it (SUMS? F). */
double hal_read_force(void);
#endif

/* The drive sample (u = K y + r, positive feedback), held until the next sample (zero-order hold). */
void hal_write_drive(double u);

/* The serial line: the next received byte, or -1 when none is waiting; when `text` is not NULL,
 * send it (a reply line, newline included) instead and return 0. */
int hal_serial(const char *text);

#endif /* SETMEM_TARGET_HAL_H */
