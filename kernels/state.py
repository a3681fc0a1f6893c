"""Loading a state from numpy into a simulation's fields (a restart), copying one state
into another, and keeping states in a history (the backward pass of ``massspring.gradient``)."""

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
def load_reals(field: ti.template(), values: ti.types.ndarray(dtype=ti.f64, ndim=1), serial: ti.template()):
    """field[i] = values[i] for the (n,) float64 ``values``, cast to the field's precision
    (``serial``: one thread, for a run of serial loops: a small one, whose every launch a
    parallel loop's start would cost several times over)."""
    ti.loop_config(serialize=serial)
    for i in range(values.shape[0]):
        field[i] = ti.cast(values[i], field.dtype)


@ti.kernel
def read_reals(field: ti.template(), out: ti.types.ndarray(dtype=ti.f64, ndim=1), serial: ti.template()):
    """out[i] = field[i] as float64 for the first len(out) entries (a read without
    ``to_numpy``'s allocation of the whole field; ``serial`` as ``load_reals``)."""
    ti.loop_config(serialize=serial)
    for i in range(out.shape[0]):
        out[i] = ti.cast(field[i], ti.f64)


@ti.kernel
def add_vector_pair(a: ti.template(), b: ti.template(), da: ti.types.ndarray(dtype=ti.f64, ndim=2),
                    db: ti.types.ndarray(dtype=ti.f64, ndim=2), serial: ti.template()):
    """a[i] += da[i], b[i] += db[i] for the (n, 3) float64 rows (an adjoint's dL/dx and
    dL/dv given a share from outside the steps: a feedback controller's; ``serial`` as
    ``load_reals``)."""
    ti.loop_config(serialize=serial)
    for i in range(da.shape[0]):
        for c in ti.static(range(3)):
            a[i][c] += da[i, c]
            b[i][c] += db[i, c]


@ti.kernel
def copy_state(dst: ti.template(), src: ti.template(), n: ti.i32, serial: ti.template()):
    """dst.x[i], dst.v[i] = src.x[i], src.v[i] for the n particles (states of one bundle;
    ``serial`` as ``load_reals``)."""
    ti.loop_config(serialize=serial)
    for i in range(n):
        dst.x[i] = src.x[i]
        dst.v[i] = src.v[i]


@ti.kernel
def save_state(hx: ti.template(), hv: ti.template(), src: ti.template(), n: ti.i32, slot: ti.i32, stride: ti.i32):
    """``store_state`` as a kernel of its own."""
    store_state(hx, hv, src, n, slot, stride)


@ti.kernel
def read_states(hx: ti.template(), hv: ti.template(), slots: ti.types.ndarray(dtype=ti.i32, ndim=1),
                xs: ti.types.ndarray(dtype=ti.f64, ndim=3), vs: ti.types.ndarray(dtype=ti.f64, ndim=3), n: ti.i32,
                stride: ti.i32):
    """xs[f], vs[f] (n, 3) = the states kept at slots[f] (m, m/s): the frames a gradient's
    run reads from its history, without copying the whole history out."""
    for f, i in ti.ndrange(slots.shape[0], n):
        row = slots[f] * stride + i
        for c in ti.static(range(3)):
            xs[f, i, c] = hx[row][c]
            vs[f, i, c] = hv[row][c]


@ti.kernel
def write_state(hx: ti.template(), hv: ti.template(), x: ti.types.ndarray(dtype=ti.f64, ndim=2),
                v: ti.types.ndarray(dtype=ti.f64, ndim=2), n: ti.i32, slot: ti.i32, stride: ti.i32):
    """The inverse of ``read_states`` for one slot: the state kept at ``slot`` = x, v (n, 3)."""
    for i in range(n):
        row = slot * stride + i
        for c in ti.static(range(3)):
            hx[row][c] = x[i, c]
            hv[row][c] = v[i, c]


@ti.func
def store_state(hx, hv, src, n, slot, stride):
    """hx[slot * stride + i], hv[...] = src.x[i], src.v[i] for the n particles."""
    for i in range(n):
        hx[slot * stride + i] = ti.cast(src.x[i], ti.f64)
        hv[slot * stride + i] = ti.cast(src.v[i], ti.f64)


@ti.func
def restore_state(hx, hv, dst, n, slot, stride):
    """The inverse of ``save_state``: dst.x[i], dst.v[i] = hx, hv[slot * stride + i]."""
    for i in range(n):
        dst.x[i] = hx[slot * stride + i]
        dst.v[i] = hv[slot * stride + i]


@ti.kernel
def read_state(src: ti.template(), out: ti.types.ndarray(dtype=ti.f64, ndim=2), n: ti.i32,
               extra: ti.template(), serial: ti.template()):
    """out[i] = (x_i, v_i, then the fields of ``extra`` at i) float64 of the state ``src``
    (m, m/s): a state read in one launch (an error-controlled run reads each step's, with
    what its integrator carries from step to step). ``extra``: a tuple of (field, first
    column, width; 0 for a scalar field), read as float64 (int32 and f32 values exactly);
    ``serial`` as ``load_reals``."""
    ti.loop_config(serialize=serial)
    for i in range(n):
        for c in ti.static(range(3)):
            out[i, c] = ti.cast(src.x[i][c], ti.f64)
            out[i, 3 + c] = ti.cast(src.v[i][c], ti.f64)
        for e in ti.static(range(len(extra))):
            if ti.static(extra[e][2] == 0):
                out[i, extra[e][1]] = ti.cast(extra[e][0][i], ti.f64)
            else:
                for c in ti.static(range(extra[e][2])):
                    out[i, extra[e][1] + c] = ti.cast(extra[e][0][i][c], ti.f64)
