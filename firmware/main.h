/* setmem-hil reference firmware: what a board's startup code calls (see main.c). */
#ifndef SETMEM_TARGET_MAIN_H
#define SETMEM_TARGET_MAIN_H

void setmem_firmware_init(void);
/* From the sample timer's interrupt: read the sensor, step the target, write the drive. */
void setmem_firmware_sample(void);
/* From the main loop: read waiting serial bytes; answers a complete line (returns 1 then). */
int setmem_firmware_poll(void);

#endif /* SETMEM_TARGET_MAIN_H */
