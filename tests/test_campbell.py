"""Full-rung Campbell diagram: the tracked (projected) method against dense eigenvalues of the full
closed loop (the independent reference) and against ARPACK solved afresh at each speed."""
import numpy as np
import pytest

from ambhil.loop.analysis import campbell_tracked, modal
from ambhil.loop.analysis.selected_eig import SelectedEig
from ambhil.loop.system import compile_system

ZETA_DRAWN = 0.5  # loop/plots.py draws modes up to this damping ratio


def _at(c, s, drawn=True):
    k = (c["speed"] == s) & ((c["zeta"] <= ZETA_DRAWN) if drawn else True)
    o = np.argsort(c["freq"][k])
    return c["freq"][k][o], c["zeta"][k][o], c["whirl"][k][o]


def _dense(m, speeds, fmax):
    """Every closed-loop mode with 0 < Im <= fmax from dense eigenvalues of the full closed loop
    at each speed (LAPACK, exact to rounding; whirl not classified)."""
    import scipy.linalg as sla
    from ambhil.loop.analysis import closed_loop
    sp_, f_, z_ = [], [], []
    for s in speeds:
        lam = sla.eigvals(closed_loop.build(m, float(s), sparse=True).dense_standard())
        lam = lam[(lam.imag > 1e-6) & (lam.imag <= fmax)]
        sp_ += [s] * len(lam)
        f_ += list(lam.imag)
        z_ += list(-lam.real / np.abs(lam))
    return {"speed": np.array(sp_), "freq": np.array(f_), "zeta": np.array(z_),
            "whirl": np.array([None] * len(f_))}


def _compare(new, ref, speeds, tol=1e-6, whirl=True):
    for s in speeds:
        f1, z1, w1 = _at(new, s)
        f0, z0, w0 = _at(ref, s)
        assert len(f1) == len(f0), f"speed {s}: {len(f1)} modes vs {len(f0)} (reference)"
        assert np.all(np.abs(f1 - f0) <= tol * f0), f"speed {s}: {np.max(np.abs(f1 - f0) / f0)}"
        assert np.all(np.abs(z1 - z0) <= tol)
        if not whirl:
            continue
        # whirl labels: equal, except inside a (near-)degenerate pair where the shapes are arbitrary
        for j in range(len(f0)):
            twin = np.abs(f0 - f0[j]) <= 1e-5 * f0[j]
            if twin.sum() == 1:
                assert w1[j] == w0[j], f"speed {s}, {f0[j]:.3f} rad/s: {w1[j]} vs {w0[j]}"
            else:
                assert sorted(w1[twin]) == sorted(w0[twin]) or s == 0.0


@pytest.mark.parametrize("scene", ["scenes/paper_3amb.toml", "scenes/rotor3m_3amb.toml"])
def test_tracked_campbell_matches_arpack(scene):
    m = compile_system(scene)
    speeds = np.linspace(0.0, 4000.0, 15)
    new = modal.campbell(m, speeds, 4400.0)
    assert "basis_size" in new  # the fast path ran (it returns its statistics)
    # frequencies and damping against dense eigenvalues of the full loop (ARPACK's own scatter,
    # up to 8e-7 relative, is too close to 1e-6 to be the reference for these)
    _compare(new, _dense(m, speeds, 4400.0), speeds, whirl=False)
    # the per-speed ARPACK path: the same modes, its values to its own accuracy, and the whirl
    # labels of both
    ref = modal.campbell(m, speeds, 4400.0, method="per-speed")
    _compare(new, ref, speeds, tol=5e-6)


def test_missing_mode_is_caught(monkeypatch):
    """Anchors that lack a mode's shape: the midpoint check finds the mode, adds its shape and
    the result is still complete."""
    m = compile_system("scenes/paper_3amb.toml")
    speeds = np.linspace(0.0, 4000.0, 9)
    orig, calls = campbell_tracked._eigs_in_disk, []

    def deficient(A, E, centre, radius, **kw):
        lam, V = orig(A, E, centre, radius, **kw)
        calls.append(1)
        if len(calls) <= 2:  # the two end speeds: drop every mode below ~95 Hz
            drop = np.abs(lam.imag) < 600
            return lam[~drop], (V[:, ~drop] if V is not None else None)
        return lam, V

    monkeypatch.setattr(campbell_tracked, "_eigs_in_disk", deficient)
    new = modal.campbell(m, speeds, 4400.0)
    assert new["checks"] > 1  # the first check failed and both halves were checked again
    monkeypatch.setattr(campbell_tracked, "_eigs_in_disk", orig)
    _compare(new, _dense(m, speeds, 4400.0), speeds, whirl=False)
    ref = modal.campbell(m, speeds, 4400.0, method="per-speed")
    _compare(new, ref, speeds, tol=5e-6)


def test_bad_method_named():
    m = compile_system("scenes/paper_3amb.toml")
    with pytest.raises(ValueError, match="method"):
        modal.campbell(m, [0.0, 1.0, 2.0], 100.0, method="fast")


def test_selected_eigenvectors_are_eigenvectors():
    """The eigenvalue-only QR plus inverse iteration for chosen eigenvalues (LAPACK dhseqr and
    dhsein through ctypes) against scipy's full eigendecomposition (dgeev)."""
    import scipy.linalg as sla
    rng = np.random.default_rng(7)
    for n in (5, 40, 90):
        S = rng.standard_normal((n, n)) * np.logspace(-3, 3, n)[:, None]  # badly scaled rows
        se = SelectedEig(n)
        lam = se.eigvals(np.asfortranarray(S))
        ref = sla.eigvals(S)
        assert all(np.min(np.abs(ref - l)) <= 1e-9 * np.max(np.abs(ref)) for l in lam)
        sel = np.where(lam.imag >= 0)[0][::2]  # real ones and upper members of complex pairs
        V = se.vectors(sel)
        assert V.shape == (n, len(sel))
        r = np.linalg.norm(S @ V - V * lam[sel], axis=0) / (np.linalg.norm(S, 2) * np.linalg.norm(V, axis=0))
        assert np.all(r <= 1e-12), r.max()


def test_band_without_modes():
    """Speeds at which no mode lies in the band (here: none at all) leave the tracked path
    with empty selections; it returns an empty diagram, like the per-speed path."""
    m = compile_system("scenes/paper_3amb.toml")
    speeds = np.linspace(0.0, 4000.0, 5)
    new = modal.campbell(m, speeds, 10.0)
    ref = modal.campbell(m, speeds, 10.0, method="per-speed")
    assert "basis_size" in new
    assert np.sum(new["zeta"] <= ZETA_DRAWN) == np.sum(ref["zeta"] <= ZETA_DRAWN) == 0
