"""particle.numba_fixes: numba's inliner copies a variable without copying its location; the
cyclic collector is held back while numba compiles."""
import copy
import gc

import numba
import pytest
from numba.core import event, ir

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


def test_the_collector_threshold_is_raised_for_the_outermost_compilation_only():
    before = gc.get_threshold()
    listener = numba_fixes.CollectorThreshold(gen0=before[0] + 1000)
    listener.on_start(None)
    assert gc.get_threshold() == (before[0] + 1000, *before[1:])
    listener.on_start(None)  # a callee compiled inside it
    listener.on_end(None)
    assert gc.get_threshold()[0] == before[0] + 1000  # still compiling the outermost
    listener.on_end(None)
    assert gc.get_threshold() == before


def test_a_compilation_that_fails_sets_the_threshold_back():
    seen = []

    class Probe(event.Listener):  # runs after the installed listener's start
        def on_start(self, ev):
            seen.append(gc.get_threshold()[0])

        def on_end(self, ev):
            pass

    before = gc.get_threshold()
    with event.install_listener("numba:compile", Probe()):
        @numba.njit
        def broken(x):
            return x + "text"

        with pytest.raises(numba.TypingError):
            broken(1.0)
    assert seen and seen[0] == max(numba_fixes.COMPILE_GEN0, before[0])
    assert gc.get_threshold() == before
