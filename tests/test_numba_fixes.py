"""particle.numba_fixes: numba's inliner copies a variable without copying its location."""
import copy

import numba
from numba.core import ir

from particle import numba_fixes


def test_a_variable_copy_shares_its_location_and_copies_its_scope():
    loc = ir.Loc("kernel.py", 3)
    loc.lines = ["line\n"] * 1000  # what numba caches on a location: its file's lines
    scope = ir.Scope(None, loc)
    a, b = scope.define("a", loc), scope.define("b", loc)
    statement = ir.Assign(b, a, loc)  # a = b
    copied = copy.deepcopy(statement)
    assert copied.target.loc is loc and copied.value.loc is loc
    assert copied.target.scope is copied.value.scope  # one scope copy per deep copy
    assert copied.target.scope is not scope
    assert copied.target.scope.get("b").name == "b"
    assert (copied.target.name, copied.value.name) == ("a", "b")


def test_installed_exactly_where_numba_lacks_it():
    assert vars(ir.Var)["__deepcopy__"] is numba_fixes._var_deepcopy or \
        numba.version_info[:2] >= numba_fixes.FIXED_IN
    assert not numba_fixes.needed()  # installed (or not needed) once particle is imported
    assert not numba_fixes.needed((0, 59))
