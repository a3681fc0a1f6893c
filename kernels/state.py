"""Loading a state from numpy into a simulation's fields (a restart)."""

import taichi as ti


@ti.kernel
def load_vectors(field: ti.template(), values: ti.types.ndarray(dtype=ti.f64, ndim=2)):
    """field[i] = values[i] for the (n, 3) float64 ``values``, cast to the field's precision."""
    for i in range(values.shape[0]):
        field[i] = ti.Vector([ti.cast(values[i, c], field.dtype) for c in ti.static(range(3))])


@ti.kernel
def load_integers(field: ti.template(), values: ti.types.ndarray(dtype=ti.i32, ndim=1)):
    """field[i] = values[i] for the (n,) int32 ``values``."""
    for i in range(values.shape[0]):
        field[i] = values[i]


@ti.kernel
def load_reals(field: ti.template(), values: ti.types.ndarray(dtype=ti.f64, ndim=1)):
    """field[i] = values[i] for the (n,) float64 ``values``, cast to the field's precision."""
    for i in range(values.shape[0]):
        field[i] = ti.cast(values[i], field.dtype)
