"""Conversions, QoS, diagnostics and stamp matching shared by every LEAP-NBV node."""
