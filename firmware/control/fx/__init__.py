"""The controllers' fixed-point twins: each file is the integer form of the float controller of
the same name in ``firmware/control/``, function for function the C of ``c/ecu_fx.c``."""
