"""Lazy loading of the JAX and Warp back ends: `import arraycontact` imports neither."""

from __future__ import annotations

import importlib

_PACKAGES = {"jax": ("arraycontact_jax", "jax"), "warp": ("arraycontact_warp", "warp")}


def load(name):
    package, dependency = _PACKAGES[name]
    try:
        importlib.import_module(dependency)
    except ImportError as e:
        raise ImportError(f"backend {name!r} needs {dependency!r}: pip install "
                          f"'arraycontact[{name}]' (or the package {dependency})") from e
    return importlib.import_module(package)
