"""Simulated devices that speak the real protocols (the other side of each wire)."""
