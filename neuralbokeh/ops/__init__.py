"""Torch image operations shared by the networks and the classical renderers: FFT convolution,
overlapping tiles, the hidden-background fill. Imports only ``neuralbokeh.core``."""
