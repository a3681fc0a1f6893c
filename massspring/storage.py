"""The Taichi arrays of a simulation, as ndarrays or as fields (see kernels/arrays.py).

An ``ArraySet`` collects array declarations, then ``build()`` makes them either
as Taichi ndarrays (compiled kernels are shared by every simulation; slower
access) or as fields placed in one SNode tree of their own (faster access; the
kernels compile again for each new tree).

Fields are reused: ``release()`` hands a set's tree to ``FieldPool``, and the next
``build()`` with the same declarations (names, dtypes, shapes) takes it back
instead of creating a tree, so the kernels already compiled for those fields serve
again. A sweep of same-size simulations (a study, a test suite) compiles once.
Destroying a tree makes Taichi recompile the kernels in use once, so the pool keeps
idle trees up to a byte budget and destroys the oldest beyond it.
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np
import taichi as ti

KINDS = ("ndarray", "field")
_NUMPY = {ti.f32: np.float32, ti.f64: np.float64, ti.i32: np.int32}


class FieldPool:
    """Idle field trees by declaration signature, at most ``budget`` bytes in all.

    It holds Taichi resources of the process's one Taichi runtime, so there is one
    pool per process (``POOL``).
    """

    def __init__(self, budget=1 << 30):
        self.budget = budget
        self._idle = OrderedDict()  # (signature, serial) -> (tree, arrays, nbytes)
        self._serial = 0

    def take(self, signature):
        for key in self._idle:
            if key[0] == signature:
                tree, arrays, _ = self._idle.pop(key)
                return tree, arrays
        return None

    def give(self, signature, tree, arrays, nbytes):
        self._serial += 1
        self._idle[(signature, self._serial)] = (tree, arrays, nbytes)
        while sum(entry[2] for entry in self._idle.values()) > self.budget:
            _, (old_tree, _, _) = self._idle.popitem(last=False)
            old_tree.destroy()

    def clear(self):
        """Destroy every idle tree."""
        while self._idle:
            _, (tree, _, _) = self._idle.popitem(last=False)
            tree.destroy()


POOL = FieldPool()


class ArraySet:
    """Arrays of one kind, declared by ``add`` and created together by ``build``."""

    def __init__(self, kind="ndarray"):
        if kind not in KINDS:
            raise ValueError(f"storage: unknown value {kind!r}, expected one of {', '.join(KINDS)}")
        self.kind = kind
        self._decls = []
        self._tree = None
        self._arrays = None

    def add(self, name, dtype, shape, element=(), values=None):
        """Declare array ``name``: ``shape`` of ``element``-shaped items of ``dtype``.

        A zero-size shape becomes one unused item (Taichi has no empty arrays).
        ``values`` (numpy, broadcastable to shape + element) fills it at build time;
        arrays without values start at zero.
        """
        shape = tuple(max(int(s), 1) for s in np.atleast_1d(shape))
        self._decls.append((name, dtype, shape, tuple(element), values))

    def vectors(self, name, dtype, n, values=None, k=3):
        self.add(name, dtype, n, (k,), values)

    def _signature(self):
        return tuple((name, dtype, shape, element) for name, dtype, shape, element, _ in self._decls)

    def build(self) -> dict:
        """Create (or take from the pool) every declared array and fill it; returns name -> array."""
        reused = POOL.take(self._signature()) if self.kind == "field" else None
        if reused is not None:
            self._tree, arrays = reused
        else:
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
            elif reused is not None:
                arrays[name].fill(0)
        self._arrays = arrays
        return arrays

    def nbytes(self) -> int:
        return sum(int(np.prod(shape + element)) * np.dtype(_NUMPY[dtype]).itemsize
                   for _, dtype, shape, element, _ in self._decls)

    def release(self):
        """Hand fields back to the pool (ndarrays are freed when no longer referenced)."""
        if self._tree is not None:
            POOL.give(self._signature(), self._tree, self._arrays, self.nbytes())
            self._tree = None
        self._arrays = None


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
