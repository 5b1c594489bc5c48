"""The pure-PyTorch reference MLS-MPM (endogsim.physics.reference); its agreement with the Warp simulator is
tests/test_physics.py::test_matches_the_pure_pytorch_reference_solver."""

import numpy as np

from endogsim.physics.reference import MPMProblem, run_mpm


def _block(n=4, spacing=0.004, **kw):
    ax = (np.arange(n) + 0.5) * spacing
    x = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3) + 0.04
    P = len(x)
    E, nu = 3000.0, 0.4
    defaults = dict(x=x, vol=np.full(P, spacing ** 3), mu=np.full(P, E / (2 * (1 + nu))),
                    lam=np.full(P, E * nu / ((1 + nu) * (1 - 2 * nu))), density=np.full(P, 1000.0),
                    anchored=np.zeros(P, bool), box_lo=np.zeros(3), box_size=0.12, grid=30, dt=1e-4,
                    substeps=10, frames=3, gravity=np.zeros(3))
    defaults.update(kw)
    return MPMProblem(**defaults)


def test_reference_free_fall_and_rest():
    # An unconstrained elastic block in uniform gravity falls as a rigid body; symplectic Euler over N
    # substeps gives x = x0 + g dt^2 N (N + 1) / 2 (g t^2 / 2 as dt -> 0).
    p = _block(gravity=np.array([0.0, 0.0, 9.81]))
    r = run_mpm(p)
    N = (p.frames - 1) * p.substeps
    dz = (r.x[-1] - r.x[0])[:, 2]
    assert np.allclose(dz, 9.81 * p.dt**2 * N * (N + 1) / 2, rtol=1e-6)
    assert np.allclose(r.F[-1], np.eye(3), atol=1e-6)
    # Without loads nothing moves.
    still = run_mpm(_block())
    assert np.abs(still.x[-1] - still.x[0]).max() < 1e-12
