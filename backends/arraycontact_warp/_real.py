"""The floating-point type every Warp kernel of this back end computes in.

Warp kernels are typed and do not mix float32 with float64 (a literal is float32), so the
kernels are written in `real`, `vec2`, `vec3`, `vec4`, `mat22` and `real(literal)`. This module
holds float32. `precision("float64")` imports the back end's module files a second time, as the
package arraycontact_warp._float64 with a float64 twin of this module in its place: the same
source, one float64 set of Warp modules, built on first use.
"""

from __future__ import annotations

import importlib
import sys
import types

import numpy as np
import warp as wp

_TYPES = {
    wp.float32: dict(real=wp.float32, vec2=wp.vec2, vec3=wp.vec3, vec4=wp.vec4, mat22=wp.mat22),
    wp.float64: dict(real=wp.float64, vec2=wp.vec2d, vec3=wp.vec3d, vec4=wp.vec4d, mat22=wp.mat22d),
}


def _names(real):
    d = dict(_TYPES[real])
    d["NP_REAL"] = np.dtype(wp.dtype_to_numpy(real))
    eps = float(np.finfo(d["NP_REAL"]).eps)
    d["EPS"] = wp.constant(real(eps))
    # |a . xi - b| below this: the constraint is active (about 1e-6 in float32).
    d["ACTIVE_TOL"] = wp.constant(real(8 * eps))
    return d


globals().update(_names(wp.float32))


def precision(dtype):
    """The back end's `_detect` module that computes in dtype ('float32' or 'float64')."""
    dt = np.dtype(dtype)
    if dt == np.float32:
        return importlib.import_module(__package__ + "._detect")
    if dt != np.float64:
        raise ValueError(f"dtype must be float32 or float64, got {dt}")
    name = __package__ + "._float64"
    if name not in sys.modules:
        pkg = types.ModuleType(name)
        pkg.__path__ = list(sys.modules[__package__].__path__)  # the same module files
        pkg.__package__ = name
        twin = types.ModuleType(name + "._real")
        twin.__dict__.update(_names(wp.float64), precision=precision)
        sys.modules[name] = pkg
        sys.modules[twin.__name__] = twin
    return importlib.import_module(name + "._detect")
