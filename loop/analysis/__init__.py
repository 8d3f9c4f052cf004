"""Frequency-domain analyses of the compiled model with its AMB loops closed."""
