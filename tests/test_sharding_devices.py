"""The other half of the JAX sharded plan's checks on four CPU devices (see
test_sharding.run_sharding_checks)."""

from test_sharding import HALF, run_sharding_checks


def test_jax_sharded_plan_on_four_cpu_devices_overflow_inputs_and_errors():
    run_sharding_checks(f"not ({HALF})", 8)
