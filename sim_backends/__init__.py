"""Simulated structures and fake devices (importable as ``setmem_hil.sim_backends``)."""
