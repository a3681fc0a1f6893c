"""The Taichi arrays of a simulation, as ndarrays or as fields (see kernels/arrays.py).

An ``ArraySet`` collects array declarations, then ``build()`` makes them either
as Taichi ndarrays (compiled kernels are shared by every simulation; slower
access) or as fields placed in one SNode tree of their own (faster access; the
kernels compile again for each new tree). ``release()`` frees the tree.
"""

from __future__ import annotations

import numpy as np
import taichi as ti

KINDS = ("ndarray", "field")
_NUMPY = {ti.f32: np.float32, ti.f64: np.float64, ti.i32: np.int32}


class ArraySet:
    """Arrays of one kind, declared by ``add`` and created together by ``build``."""

    def __init__(self, kind="ndarray"):
        if kind not in KINDS:
            raise ValueError(f"storage: unknown value {kind!r}, expected one of {', '.join(KINDS)}")
        self.kind = kind
        self._decls = []
        self._tree = None

    def add(self, name, dtype, shape, element=(), values=None):
        """Declare array ``name``: ``shape`` of ``element``-shaped items of ``dtype``.

        A zero-size shape becomes one unused item (Taichi has no empty arrays).
        ``values`` (numpy, broadcastable to shape + element) fills it at build time.
        """
        shape = tuple(max(int(s), 1) for s in np.atleast_1d(shape))
        self._decls.append((name, dtype, shape, tuple(element), values))

    def vectors(self, name, dtype, n, values=None, k=3):
        self.add(name, dtype, n, (k,), values)

    def build(self) -> dict:
        """Create every declared array and fill the given values; returns name -> array."""
        arrays = {}
        builder = ti.FieldsBuilder() if self.kind == "field" else None
        for name, dtype, shape, element, _ in self._decls:
            arrays[name] = _make(builder, dtype, shape, element)
        if builder is not None:
            self._tree = builder.finalize()
        for name, dtype, shape, element, values in self._decls:
            if values is not None:
                data = np.zeros(shape + element, dtype=_NUMPY[dtype])
                values = np.asarray(values)
                if values.size:
                    data[tuple(slice(0, s) for s in values.shape)] = values
                arrays[name].from_numpy(data)
        return arrays

    def nbytes(self) -> int:
        return sum(int(np.prod(shape + element)) * np.dtype(_NUMPY[dtype]).itemsize
                   for _, dtype, shape, element, _ in self._decls)

    def release(self):
        """Free the fields' SNode tree (ndarrays are freed when no longer referenced)."""
        if self._tree is not None:
            self._tree.destroy()
            self._tree = None


def _make(builder, dtype, shape, element):
    if builder is None:
        if not element:
            return ti.ndarray(dtype, shape=shape)
        if len(element) == 1:
            return ti.Vector.ndarray(element[0], dtype, shape=shape)
        return ti.Matrix.ndarray(element[0], element[1], dtype, shape=shape)
    if not element:
        field = ti.field(dtype)
    elif len(element) == 1:
        field = ti.Vector.field(element[0], dtype)
    else:
        field = ti.Matrix.field(element[0], element[1], dtype)
    builder.dense(ti.axes(*range(len(shape))), shape).place(field)
    return field
