"""Transports and device front-ends (importable as ``setmem_hil.drivers``)."""
