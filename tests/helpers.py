"""Small scene builders for tests (dict -> validated Scene)."""
from __future__ import annotations

import copy

from ambhil.loop.scene import parse_scene

BASE = {
    "scene": {"name": "test"},
    "model": {"rung": "full"},
    "shaft": [{"length": 1.0, "outer_diameter": 0.05, "elements": 20}],
    "amb": [
        {"name": "A", "node": 3, "gap": 5e-4, "bias_current": 1.0, "turns": 100, "pole_area": 5e-4},
        {"name": "B", "node": 19, "gap": 5e-4, "bias_current": 1.0, "turns": 100, "pole_area": 5e-4},
    ],
    "sensor": {"gain": 1.0e4, "time_constant": 0.0},
    "amplifier": {"gain": 1.0, "time_constant": 0.0},
    "controller": {"kp": 1.0},
    "speed": {"value": 0.0},
}


def scene(**over):
    d = copy.deepcopy(BASE)
    for k, v in over.items():
        if v is None:
            d.pop(k, None)
        else:
            d[k] = v
    return parse_scene(d, "test.toml")


def raw(**over):
    d = copy.deepcopy(BASE)
    d.update(over)
    return d
