"""Filling a device bundle: every declared value in one kernel launch.

``plan`` (from ``device.Layout``) groups the fields by item count; each group is
(whether its fields are 0-D, the index in ``where`` of its first entry's offset, its
entries), each entry (field name, whether int32, element
shape, values per item), the values read from one float64 and one int32 buffer. The
counts and offsets are not in the plan but in ``where`` (int64: each group's item count,
then each entry's offset in its buffer, in plan order), so models of other sizes that
share a bundle's fields share its compiled kernel."""

import taichi as ti


@ti.func
def read_element(source: ti.template(), base, element: ti.template(), dtype: ti.template()):
    """Item of ``element`` shape starting at ``source[base]``, cast to ``dtype``."""
    if ti.static(len(element) == 0):
        return ti.cast(source[base], dtype)
    elif ti.static(len(element) == 1):
        return ti.Vector([ti.cast(source[base + c], dtype) for c in ti.static(range(element[0]))], dtype)
    else:
        return ti.Matrix([[ti.cast(source[base + r * element[1] + c], dtype) for c in ti.static(range(element[1]))]
                          for r in ti.static(range(element[0]))], dtype)


@ti.func
def read_item(base, field: ti.template(), entry: ti.template(), reals: ti.template(), ints: ti.template()):
    """The item of one plan entry starting at ``base`` in its buffer."""
    if ti.static(entry[1]):
        return read_element(ints, base, entry[2], field.dtype)
    else:
        return read_element(reals, base, entry[2], field.dtype)


@ti.kernel
def fill(dev: ti.template(), plan: ti.template(), reals: ti.types.ndarray(dtype=ti.f64, ndim=1),
         ints: ti.types.ndarray(dtype=ti.i32, ndim=1), where: ti.types.ndarray(dtype=ti.i64, ndim=1)):
    """Store the declared values of a bundle's fields in one launch, one loop per group.
    (``from_numpy`` compiles a kernel for every field: a new bundle of many fields would
    compile many loops instead of this one kernel.)"""
    for g in ti.static(range(len(plan))):
        scalar, first, entries = ti.static(plan[g])
        if ti.static(scalar):
            for k in ti.static(range(len(entries))):
                field = ti.static(getattr(dev, entries[k][0]))
                field[None] = read_item(where[first + k], field, entries[k], reals, ints)
        else:
            for i in range(ti.cast(where[g], ti.i32)):
                for k in ti.static(range(len(entries))):
                    field = ti.static(getattr(dev, entries[k][0]))
                    base = where[first + k] + ti.cast(i, ti.i64) * entries[k][3]
                    field[i] = read_item(base, field, entries[k], reals, ints)
