"""distributed/: training with several processes."""
