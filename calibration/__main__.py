"""``python -m calibration --scene FILE --reference PATH --out PATH [--verbose]``.

Under ``mpirun -n N`` rank 0 runs the calibration and ranks 1..N-1 evaluate
test points (:mod:`calibration.pool`).
"""
import sys

from calibration.cli import main

sys.exit(main())
