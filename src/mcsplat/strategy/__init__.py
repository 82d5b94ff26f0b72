"""Densification strategies behind one protocol: MCMC (the paper) and ADC (the 3DGS baseline)."""

from .adc import ADCConfig, ADCSchedule, ADCStrategy
from .base import Strategy
from .mcmc import MCMCConfig, MCMCSchedule, MCMCStrategy

__all__ = ["Strategy", "MCMCConfig", "MCMCSchedule", "MCMCStrategy", "ADCConfig", "ADCSchedule", "ADCStrategy"]
