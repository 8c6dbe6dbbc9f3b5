"""setmem-hil: set-membership identification and robust-performance-driven input design
for lightly damped flexible structures, on simulated or real (serial, CAN, Modbus) rigs.

The numerical core (modal model, identification, mixed mu, input design) is free of I/O;
files, devices and the terminal are handled at the edges (``*_file`` modules, ``drivers``,
``commands``).
"""

__version__ = "0.1.0"
