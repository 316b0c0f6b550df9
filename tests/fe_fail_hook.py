"""``python -m reference_fe`` with the FE runs of chosen test vertices failing, for the tests:
a failure provoked deterministically (the real solver never runs for those items), on every
rank of an ``mpirun``.

``FORCECAL_TEST_FAIL="relaxation:12,indentation:40"`` makes the relaxation of vertex 12 and
the indentation of vertex 40 raise :class:`~forcecal.errors.ConvergenceError` as a march that
gave up would (``gravity_static`` fails the static sag). Usage::

    mpirun -n 2 python tests/fe_fail_hook.py --scene ... --out ...
"""

import os
import sys

from forcecal.errors import ConvergenceError

import reference_fe.run


def failing(spec: str):
    """``compute_item`` with the items of ``spec`` failing."""
    fail = {(kind, int(v) if v.lstrip("-").isdigit() else -1)
            for kind, _, v in (part.partition(":") for part in spec.split(",") if part)}
    original = reference_fe.run.compute_item

    def compute_item(model, scene, problem, item, fe=None, after=None):
        vertex = int(problem.test_points[item.point]) if item.point >= 0 else -1
        if (item.kind, vertex) in fail:
            error = ConvergenceError(f"test hook: the {item.kind} of vertex {vertex} diverges")
            error.reached = 0.5
            raise error
        return original(model, scene, problem, item, fe, after)
    return compute_item


def install(spec: str) -> None:
    reference_fe.run.compute_item = failing(spec)


if __name__ == "__main__":
    from reference_fe.__main__ import main

    install(os.environ.get("FORCECAL_TEST_FAIL", ""))
    sys.exit(main(sys.argv[1:]))
