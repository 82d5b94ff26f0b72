"""strategy/: MCMC (relocation, noise, health), ADC and --cap-max auto."""
