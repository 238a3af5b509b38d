"""What every stage runs on: the process pool, progress reporting, atomic outputs and locks."""
