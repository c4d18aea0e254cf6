"""HIL/SIL side of the project: everything with I/O, the plant models and the CLIs."""
