"""Densification strategies behind one protocol: MCMC (the paper) and ADC (the 3DGS baseline)."""

from .adc import ADCConfig, ADCStrategy
from .base import Strategy
from .mcmc import MCMCConfig, MCMCStrategy

__all__ = ["Strategy", "MCMCConfig", "MCMCStrategy", "ADCConfig", "ADCStrategy"]
