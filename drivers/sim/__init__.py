"""Simulators that speak each device's real protocol."""
