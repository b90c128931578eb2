"""Warp back end of arraycontact (kernels for GPU simulators).

The kernels come with the Warp back-end issue; until then `arraycontact.detect(...,
backend="warp")` raises a ValueError that says so."""

AVAILABLE = False
