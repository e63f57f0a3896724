"""Batched two-mass plant, drive, measurement, test signal and records (SI units)."""
