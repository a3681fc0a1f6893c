"""Sums over particles in fixed blocks: the same result on any number of threads.

A reduction written as ``total += row(i)`` in a parallel loop adds the threads'
partial sums in whatever order they finish, so its rounding depends on the
thread count. Here every reduction sums particles ``[b * BLOCK, (b + 1) * BLOCK)``
in order into ``partial[b]`` (in parallel over blocks), then adds the blocks in
order in a serial loop. The serial drivers run the same code, so serial and
parallel runs agree to the bit.

Usage inside a ``ti.func`` (the pattern, since a ti.func cannot take another as
a callback with its own arguments)::

    for b in range(block_count(n)):
        acc = ti.Vector.zero(ti.f64, 3)
        for i in range(b * BLOCK, block_end(b, n)):
            acc += ...
        dev.partial[b] = acc
    return ordered_sum(dev.partial, block_count(n))
"""

import taichi as ti

BLOCK = 256  # particles per block


@ti.func
def block_count(n):
    return (n + BLOCK - 1) // BLOCK


@ti.func
def block_end(b, n):
    return ti.min(n, (b + 1) * BLOCK)


@ti.func
def ordered_sum(partial: ti.template(), count):
    """Sum of ``partial[0:count]`` (vectors of float64) in index order, serially."""
    total = ti.Vector.zero(ti.f64, partial.n)
    ti.loop_config(serialize=True)
    for b in range(count):
        total += partial[b]
    return total
