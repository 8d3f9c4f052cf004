"""A controller in its own process: your law, and one call that joins the run.

    python examples/thin_client/my_controller.py --run-id mine --connect tcp/127.0.0.1:7447

The law here is the testbench's PID in numpy, from the coefficients the plant announces
(``meta.discrete``): it answers exactly as ``ambhil controller`` does
(tests/test_law_client.py).  Put yours in its place (docs/controllers.md).
"""
import argparse
import sys

import numpy as np

from ambhil.bridge.process.law_client import serve


class MyLaw:
    def __init__(self, meta):                  # meta: axes, period, u_op, discrete, params, ...
        d = meta.discrete
        self.I, self.D, self.kp, self.aw = d["integral"], d["derivative"], d["kp"], d["anti_windup"]
        self.u_max = d["input_limit"] or np.inf
        self.u_op = np.array(meta.u_op)
        self.reset()

    def reset(self):                           # the integrator holds u_op at y = 0
        self.xi = self.u_op / self.I["c"] if self.I["c"] else 0.0 * self.u_op
        self.xd = 0.0 * self.u_op

    def step(self, t, y):                      # sensor outputs -> amplifier inputs
        I, D, e = self.I, self.D, -y
        ui = I["c"] * self.xi + I["d"] * e
        ud = D["c"] * self.xd + D["d"] * e
        self.xd = D["a"] * self.xd + D["b"] * e
        u = self.kp * e + ui + ud
        hold = self.aw & (np.abs(u) > self.u_max) & (e * u > 0)    # anti-windup
        self.xi = np.where(hold, self.xi, I["a"] * self.xi + I["b"] * e)
        return u


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description="my controller, joining an ambhil run")
    ap.add_argument("--run-id", required=True)
    ap.add_argument("--connect", nargs="+", required=True, help="the plant's endpoint(s)")
    a = ap.parse_args()
    summary = serve(MyLaw, run_id=a.run_id, connect=a.connect)
    print(f"my_controller: {summary['steps']} samples answered; fault: {summary['fault']}")
    sys.exit(1 if summary["fault"] else 0)
