"""Lazy loading of the JAX and Warp back ends: `import arraycontact` imports neither."""

from __future__ import annotations

import importlib

_PACKAGES = {"jax": ("arraycontact_jax", "jax"), "warp": ("arraycontact_warp", "warp")}


def resolve(name):
    """The back end that `backend="auto"` means: Warp when it imports (its kernels run on a
    visible CUDA GPU, else on the CPU, where they are about 10x faster than the NumPy back end
    at 2^16 nodes), else NumPy. Any other name is returned as it is."""
    if name != "auto":
        return name
    try:
        importlib.import_module("warp")
    except ImportError:
        return "numpy"
    return "warp"


def load(name):
    package, dependency = _PACKAGES[name]
    try:
        importlib.import_module(dependency)
    except ImportError as e:
        raise ImportError(
            f"backend {name!r} needs {dependency!r}: pip install "
            f"'arraycontact[{name}]' (or the package {dependency})"
        ) from e
    return importlib.import_module(package)


def quiet_warp():
    """Warp without its banner and kernel-cache lines (reports and tests print their own):
    `config.log_level` on Warp >= 1.10, where `config.quiet` is deprecated and ignored."""
    import warp as wp

    if hasattr(wp, "LOG_WARNING"):
        wp.config.log_level = wp.LOG_WARNING
    else:
        wp.config.quiet = True
