"""``massspring.solvers.minres`` (a Newton-solved step's adjoint solve) against numpy's
dense solves of symmetric indefinite systems."""

import numpy as np
import pytest

from massspring.solvers.minres import minres


def indefinite_system(n=60, seed=0):
    """(A, B, b): A = S - U C U^T, S symmetric positive definite less a rank-5 positive
    part large enough to make A indefinite (as the definiteness fix's S and the true
    Jacobian J of a folding cloth), B = the inverse of S's diagonal."""
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, n))
    s = q @ q.T + n * np.eye(n)
    u = rng.normal(size=(n, 5))
    a = s - u @ np.diag([80.0, 120.0, 200.0, 300.0, 500.0]) @ u.T
    return a, np.diag(1.0 / np.diag(s)), rng.normal(size=n)


def b_norm(b_matrix, r):
    return float(np.sqrt(r @ b_matrix @ r))


def test_solves_a_symmetric_indefinite_system():
    a, b_matrix, b = indefinite_system()
    assert np.linalg.eigvalsh(a).min() < 0 < np.linalg.eigvalsh(a).max()
    out = minres(lambda v: a @ v, lambda r: b_matrix @ r, b, np.zeros_like(b), 1e-10, 500)
    exact = np.linalg.solve(a, b)
    assert out.converged and out.reason == "converged"
    assert out.iterations < 60  # at most the dimension, in exact arithmetic
    assert np.abs(out.x - exact).max() <= 1e-8 * np.abs(exact).max()
    assert out.residual == pytest.approx(b_norm(b_matrix, b - a @ out.x) / b_norm(b_matrix, b), rel=1e-6)


def test_the_residual_never_grows_with_more_iterations():
    """MINRES minimises the residual's B-norm over a growing Krylov space: stopping after k
    iterations, for k = 1..20, gives residuals that never rise (a wrong recurrence or
    rotation breaks this long before it breaks convergence)."""
    a, b_matrix, b = indefinite_system(seed=1)
    x0 = np.full_like(b, 0.1)
    residuals = [minres(lambda v: a @ v, lambda r: b_matrix @ r, b, x0, 1e-14, k).residual for k in range(1, 21)]
    assert all(later <= earlier * (1 + 1e-12) for earlier, later in zip(residuals, residuals[1:])), residuals
    assert residuals[-1] < 0.5 * residuals[0]


def test_a_warm_start_at_the_solution_takes_no_iteration():
    a, b_matrix, b = indefinite_system(seed=2)
    exact = np.linalg.solve(a, b)
    out = minres(lambda v: a @ v, lambda r: b_matrix @ r, a @ exact, exact, 1e-8, 100)
    assert out.converged and out.iterations == 0


def test_running_out_of_iterations_is_a_reason_not_an_exception():
    a, b_matrix, b = indefinite_system(seed=3)
    out = minres(lambda v: a @ v, lambda r: b_matrix @ r, b, np.zeros_like(b), 1e-12, 5)
    assert not out.converged and out.reason == "max_iter" and out.iterations == 5 and 0 < out.residual < 1


def test_an_inconsistent_singular_system_stops_without_converging():
    """b outside A's range: no x solves it; MINRES reaches the least-squares residual and
    stops (stalled or out of iterations), never reporting convergence."""
    a, b_matrix, b = indefinite_system(seed=4)
    w, v = np.linalg.eigh(a)
    w[np.argmin(np.abs(w))] = 0.0
    singular = (v * w) @ v.T
    out = minres(lambda x: singular @ x, lambda r: b_matrix @ r, b, np.zeros_like(b), 1e-10, 400)
    assert not out.converged and out.reason in ("stalled", "max_iter")


def test_an_indefinite_preconditioner_is_reported():
    a, _, b = indefinite_system(seed=5)
    out = minres(lambda v: a @ v, lambda r: -r, b, np.zeros_like(b), 1e-8, 50)
    assert out.reason == "indefinite" and not out.converged
