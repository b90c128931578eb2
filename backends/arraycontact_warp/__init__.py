"""Warp back end of arraycontact (kernels for GPU simulators): not implemented yet."""


def run_one_shot(slave_x, master, prep, st, dtype):
    raise NotImplementedError("the Warp back end is not implemented yet (issue: Warp back end)")
