"""Real instruments: device profiles and the generic drivers that interpret them.

* :mod:`.profile`: instrument profiles (TOML): identity, init sequence, command templates,
  register maps, limits; shipped ones in ``profiles/``, or a user's file.
* :mod:`.scpi_commands`: SCPI headers (canonical short form), templates, number parsing.
* :mod:`.visa_link`: a PyVISA (pyvisa-py) session with one-line errors.
* :mod:`.scpi_generator` / :mod:`.modbus_generator`: function generators and shaker
  controllers (the :class:`~setmem_hil.drivers.instruments.source.SignalSource` protocol).
* :mod:`.lockin`: lock-in amplifiers (phasor readings).
* :mod:`.phasor_dwell`: the stepped-sine Experiment over a source and two lock-ins (safety,
  closed-loop level, settling test, bound from the scatter).
* :mod:`.instrument_set`: opens every instrument a procedure names, and ``probe``.
"""
