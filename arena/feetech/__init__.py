"""Feetech STS3215 servo bus: packet codec, registers, calibration, bus access, simulated bus."""
