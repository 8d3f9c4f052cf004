"""The figures of docs/faults.md "What was checked": blade-loss orbit ratios against linearity, and
the dominant pole after losing one of three AMBs against `analyze` (continuous eigenvalues) and the
exact sampled loop of the scene without that AMB.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python -m docs.tools.fault_checks

Same computations as tests/test_faults.py (which asserts them); prints one line per node / case.
"""
from __future__ import annotations

import os

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def main() -> None:
    from ambhil.loop.analysis import modal
    from ambhil.loop.numerics import identify_poles, sampled_loop
    from ambhil.loop.scene import load_scene, with_fault_flags
    from ambhil.loop.orbits import harmonic
    from ambhil.loop.simulation import simulate
    from ambhil.loop.system import compile_system
    s = load_scene(os.path.join(ROOT, "scenes", "paper_3amb.toml"))
    u, W, T = s.plant.unbalances[0], s.plant.simulation.speed, s.period
    print("blade loss (modal rung, step at 0.6 s of 1.2 s): steady orbit before -> after, ratio vs (m + dm e^{i dphi})/m")
    for dm, dphi in ((0.0015, 0.0), (0.001, 2.0)):
        spec = f"unbalance_step:at=0.6s,node={u.node + 1},magnitude={dm},phase={u.phase + dphi}"
        r = simulate(compile_system(with_fault_flags(s, [spec]), rung="modal"), 1.2)
        exp = (u.magnitude + dm * np.exp(1j * dphi)) / u.magnitude
        for j, nd in enumerate(r.nodes):
            b = harmonic(r.t[r.t < 0.6], r.orbit[r.t < 0.6, j, 0], W)
            a = harmonic(r.t, r.orbit[:, j, 0], W, t_from=0.9)
            print(f"  dm {dm:g} kg m, dphi {dphi:g} rad, node {nd}: {abs(b) * 1e6:.3f} -> {abs(a) * 1e6:.3f} um, "
                  f"ratio {a / b:.4f}, expected {exp:.4f}, error {abs(a / b - exp) / abs(exp):.1e}")
    sc = s.with_controller(kp=0.35 * s.controller.kp).with_plant(unbalances=())
    print("AMB loss (full rung, kp x 0.35, no unbalance, 2 um initial displacement, trapezoidal): dominant pole, 1/s")
    for lost in "AB":
        wo = compile_system(sc.with_plant(ambs=tuple(a for a in sc.plant.ambs if a.name != lost)), rung="full")
        lam = max(modal.Solver(wo).all(W, 2 * np.pi * 5e3), key=lambda m: m.eigenvalue.real).eigenvalue
        ex = sampled_loop(wo, "zoh", speed=W)
        m = compile_system(with_fault_flags(sc, [f"amb_loss:at=0.05s,axis={lost}"]), rung="full")
        q0 = np.zeros(m.n)
        q0[m.act_dof[0]] = 2e-6
        r = simulate(m, 0.8, q0=q0, integrator="trapezoidal")
        keep = [k for k, (nm, _) in enumerate(m.axes) if nm != lost]
        mu = identify_poles(r.y[r.t > 0.06][:, keep])
        d = (np.log(mu.astype(complex)) / T)[int(np.argmax(np.abs(mu)))]
        print(f"  without {lost}: analyze {lam.real:.3f} {lam.imag:+.2f}i ({lam.imag / 2 / np.pi:.2f} Hz, "
              f"{'unstable' if lam.real > 0 else 'stable'}); exact sampled loop {ex.growth_rate:.3f} at "
              f"{ex.frequency_hz:.2f} Hz; simulated (ERA) {d.real:.3f} {abs(d.imag):+.2f}i")


if __name__ == "__main__":
    main()
