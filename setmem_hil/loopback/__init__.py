"""Loopback rigs (drivers + fake devices) and the transport fault survey."""
