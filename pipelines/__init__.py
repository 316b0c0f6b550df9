"""Pipelines chaining mesh -> FE reference -> calibration -> gravity comparison -> report."""
