"""The matrix-free system operator of the linearised implicit step (seed Eq. 13-15).

Eq. 15's matrix is A = M - dt D - dt^2 K. For one spring with unit direction n,
length l and rest length l0, Eq. 13-14 give the blocks (typos fixed)

    K_ii = K_jj = -K_ij = -K_ji = ks (c I - (1 + c) n n^T),   c = l0/l - 1
    D_ii = D_jj = -D_ij = -D_ji = -kd n n^T

so the spring adds S = a I + b n n^T to the (i,i) and (j,j) blocks of A and -S to
(i,j) and (j,i), with

    a = -dt^2 ks c,    b = dt kd + dt^2 ks (1 + c).

Definiteness fix (Choi & Ko 2002): K_ii = ks(-n n^T + c (I - n n^T)); the
transverse part is positive for a compressed spring (c > 0), which can make A
indefinite. With the fix, c is replaced by min(c, 0) (the along-spring term
-ks n n^T is kept), and A is symmetric positive definite. Without it, Eq. 13 is
used as written.

The global matrix is never formed: ``entry_coefficients`` stores (n, a, b) once per
step for every entry of the per-particle spring lists (each spring twice, once at
each end: the operator then streams its coefficients in order instead of looking
them up through the spring index, which measured 1.1-1.7x faster on this machine,
benchmarks/switch_point.py), and ``apply_row`` gathers (A p)_i over particle i's
springs:

    (A p)_i = m_i p_i + sum_s [a_s (p_i - p_j) + b_s n_s (n_s . (p_i - p_j))].

Shapes (n particles, m springs): ``offsets`` (n+1,), ``other``, ``spring`` (2m,)
int32 (see ``Model.adjacency``); ``coef`` (2m,) of 5-vectors (n_x, n_y, n_z, a, b)
in adjacency order; ``minv`` (n,) of 3x3 matrices (inverse diagonal blocks, the
block-Jacobi preconditioner); vectors ``p``, ``q`` (n,) of vec3.
"""

import taichi as ti

from .arrays import array_kernel
from .forces import spring_direction


@array_kernel
def entry_coefficients(x: ti.types.ndarray(), offsets: ti.types.ndarray(), other: ti.types.ndarray(),
                       spring: ti.types.ndarray(), ks: ti.types.ndarray(), kd: ti.types.ndarray(),
                       l0: ti.types.ndarray(), coef: ti.types.ndarray(), dt: ti.f64,
                       definiteness_fix: ti.template(), has_damping: ti.template(), serial: ti.template(),
                       real: ti.template()):
    """Per adjacency entry: direction n and the coefficients a, b of S = a I + b n n^T (Eq. 13-15).

    The two entries of a spring get n and -n (exactly: x_j - x_i negates exactly), so
    the same n n^T, a and b. A spring of zero length (see ``spring_direction``) gets
    n = 0 and a = 0. ``serial`` serialises the loop (small systems).
    """
    h = ti.cast(dt, real)
    ti.loop_config(serialize=serial)
    for i in range(offsets.shape[0] - 1):
        for e in range(offsets[i], offsets[i + 1]):
            s = spring[e]
            n, length = spring_direction(x[other[e]] - x[i], real)
            c = ti.cast(0, real)
            if n.norm_sqr() > 0:
                c = l0[s] / length - 1
                if ti.static(definiteness_fix):
                    c = ti.min(c, 0)
            a = -h * h * ks[s] * c
            b = h * h * ks[s] * (1 + c)
            if ti.static(has_damping):
                b += h * kd[s]
            coef[e] = ti.Vector([n[0], n[1], n[2], a, b], real)


@ti.func
def apply_row(i, p: ti.template(), mass: ti.template(), offsets: ti.template(), other: ti.template(),
              coef: ti.template(), real: ti.template()):
    """(A p)_i for the matrix-free A of Eq. 15; p must be zero at fixed particles."""
    pi = p[i]
    out = mass[i] * pi
    for e in range(offsets[i], offsets[i + 1]):
        c = coef[e]
        n = ti.Vector([c[0], c[1], c[2]], real)
        dp = pi - p[other[e]]
        out += c[3] * dp + c[4] * n.dot(dp) * n
    return out


@ti.func
def diagonal_block(i, mass: ti.template(), offsets: ti.template(), coef: ti.template(),
                   real: ti.template()):
    """The 3x3 block A_ii = m_i I + sum_s (a_s I + b_s n_s n_s^T)."""
    block = mass[i] * ti.Matrix.identity(real, 3)
    for e in range(offsets[i], offsets[i + 1]):
        c = coef[e]
        n = ti.Vector([c[0], c[1], c[2]], real)
        block += c[3] * ti.Matrix.identity(real, 3) + c[4] * n.outer_product(n)
    return block
