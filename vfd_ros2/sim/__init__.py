"""Simulated drives that speak the real wire protocols."""
