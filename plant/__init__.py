"""Rotor, bearings, model rungs and integrators."""
