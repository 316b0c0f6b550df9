"""Calibration of the particle model's connector parameters against the FE reference."""
