"""planning/: the run's plan and --budget."""
