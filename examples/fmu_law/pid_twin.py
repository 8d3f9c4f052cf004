"""The law of pid_law.c written in Python: the same operations in the same order, so that the FMU
and this class give the same doubles (tests/test_law_fmu.py runs both in the loop)::

    ambhil simulate scenes/paper_3amb.toml --law examples/fmu_law/pid_twin.py:PIDTwin
"""
import numpy as np

from build_fmu import START      # the FMU's start values (this folder is importable while a law loads)


class PIDTwin:
    def __init__(self, meta):
        p = {**START, **meta.params}
        self.kp, self.ki, self.kd, self.td = (float(p[k]) for k in ("kp", "ki", "kd", "td"))
        self.h = meta.period
        self.u_op = np.array(meta.u_op, float)
        self.reset()

    def reset(self):
        n = len(self.u_op)
        self.i, self.d, self.e_prev = np.zeros(n), np.zeros(n), np.zeros(n)

    def step(self, t, y):
        e = -y
        d = (self.td * self.d + self.kd * (e - self.e_prev)) / (self.td + self.h)
        u = self.u_op + self.kp * e + self.i + d
        self.i = self.i + self.ki * self.h * e
        self.d, self.e_prev = d, e
        return u
