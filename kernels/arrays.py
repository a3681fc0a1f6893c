"""Kernels that take their arrays either as Taichi ndarrays or as Taichi fields.

The two kinds trade compile time against speed (measured on this project's 2-core
CPU machine, see benchmarks/): a kernel with ``ti.types.ndarray()`` arguments is
compiled once per dtype and feature set and then serves every simulation, but its
array accesses are slower (the CG solve of a 128 x 128 cloth ran about 2x slower
than on fields); a kernel with field (``ti.template()``) arguments is compiled
again for every new set of fields. Small, short-lived simulations (tests, sweeps)
want ndarrays; large ones want fields.

``array_kernel`` compiles a kernel written with ``ti.types.ndarray()`` annotations
in both forms from the same source and picks the form by the type of its first
array argument at each call.
"""

import functools
import inspect
import types

import taichi as ti
from taichi.lang.field import Field
from taichi.types.ndarray_type import NdarrayType


def array_kernel(fn):
    """Like ``ti.kernel``; the ``ti.types.ndarray()`` arguments may also be fields.

    All array arguments of one call must be of the same kind.
    """
    params = list(inspect.signature(fn).parameters)
    annotations = fn.__annotations__
    first = next(k for k, name in enumerate(params) if isinstance(annotations.get(name), NdarrayType))
    on_ndarrays = ti.kernel(fn)
    twin = types.FunctionType(fn.__code__, fn.__globals__, fn.__name__, fn.__defaults__, fn.__closure__)
    twin.__annotations__ = {name: ti.template() if isinstance(a, NdarrayType) else a
                            for name, a in annotations.items()}
    twin.__qualname__ = fn.__qualname__ + "_on_fields"
    on_fields = ti.kernel(twin)

    @functools.wraps(fn)
    def launch(*args):
        return (on_fields if isinstance(args[first], Field) else on_ndarrays)(*args)

    launch.on_ndarrays = on_ndarrays
    launch.on_fields = on_fields
    return launch
