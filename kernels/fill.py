"""Filling a device bundle: every declared value in one kernel launch.

``plan`` (from ``device.Layout``) groups the fields by item count (0: a 0-D field); each
entry is (field name, whether int32, offset in its buffer, element shape, values per
item), the values read from one float64 and one int32 buffer."""

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
def read_item(i, field: ti.template(), entry: ti.template(), reals: ti.template(), ints: ti.template()):
    """Item i of one plan entry, read from its buffer."""
    if ti.static(entry[1]):
        return read_element(ints, entry[2] + i * entry[4], entry[3], field.dtype)
    else:
        return read_element(reals, entry[2] + i * entry[4], entry[3], field.dtype)


@ti.kernel
def fill(dev: ti.template(), plan: ti.template(), reals: ti.types.ndarray(dtype=ti.f64, ndim=1),
         ints: ti.types.ndarray(dtype=ti.i32, ndim=1)):
    """Store the declared values of a bundle's fields in one launch, one loop per item
    count. (``from_numpy`` compiles a kernel for every field: a new bundle of many
    fields would compile many loops instead of this one kernel.)"""
    for count, entries in ti.static(plan):
        if ti.static(count == 0):
            for entry in ti.static(entries):
                ti.static(getattr(dev, entry[0]))[None] = read_item(0, ti.static(getattr(dev, entry[0])), entry,
                                                                 reals, ints)
        else:
            for i in range(count):
                for entry in ti.static(entries):
                    field = ti.static(getattr(dev, entry[0]))
                    field[i] = read_item(i, field, entry, reals, ints)
