"""The in-process reference of the lockstep loop: plant and controller step objects (the
duck-typed interface of bridge/process/plant_node.py) in one process, same arithmetic as lockstep
over zenoh, which must reproduce it bit for bit."""
from __future__ import annotations

import numpy as np


def run_inprocess(plant, controller, n_steps: int, delay_samples: int = 0):
    """Reference loop in one process with the lockstep arithmetic.
    Returns ``(Y, U)``: Y[k] = sample k (n_steps+1 rows), U[k] = currents applied k -> k+1."""
    n = plant.n_axes
    Y = np.empty((n_steps + 1, n))
    U = np.empty((n_steps, n))
    ring = np.zeros((delay_samples + 1, n))
    y = np.asarray(plant.reset(), dtype=float)
    controller.reset()
    for k in range(n_steps):
        Y[k] = y
        c = np.asarray(controller.step(y), dtype=float)
        if delay_samples:
            ring[k % (delay_samples + 1)] = c
            u = ring[(k - delay_samples) % (delay_samples + 1)] if k >= delay_samples else np.zeros(n)
        else:
            u = c
        U[k] = u
        y = np.asarray(plant.advance(u), dtype=float)
    Y[n_steps] = y
    return Y, U
