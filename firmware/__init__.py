"""The ECU firmware: pure, deterministic, fixed-step. No I/O, no clock, no randomness."""
