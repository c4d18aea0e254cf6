"""Controllers of the four working modes. Each maps the ECU's signals to a force command (N)."""
