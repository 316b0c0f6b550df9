"""The choice rule of the whole-body data study (studies/body_data.py) on made-up scores."""
import pytest

from studies.body_data import EVERY_KIND, choose


def _fit(scores: dict[str, float], left_out: float = 0.0) -> dict:
    """A row of a fit of every kind whose cross-validation scored ``scores`` (round 2)."""
    return {"body": {"cv": {"round_2": {name: {"score": s, "left_out": left_out}
                                        for name, s in scores.items()}}}}


def test_one_volume_term_chooses_among_sets_the_fewer_kinds_on_a_tie():
    """One fit: the lowest score, a set with fewer kinds within 1 % of it wins, and the
    compression's left-out residual (the same for every set) plays no part."""
    result = {"scenes": {"a": {"rows": {EVERY_KIND: _fit(
        {"none": 1.0, "modes": 0.60, "modes+loaded_modes": 0.503, EVERY_KIND: 0.50},
        left_out=0.3)}}}}
    choice = choose(result)
    assert choice["chosen"] == "modes+loaded_modes"
    assert choice["scores"]["modes"] == pytest.approx(0.60)


def test_two_volume_terms_compare_scores_with_their_left_out_residuals():
    """Fits with the elastic and the viscoelastic term: each candidate is a set with a volume
    term, scored with its fit's left-out residual (here it reverses the order the bare
    scores give), and a tie between the volume terms goes to the elastic one."""
    rows = {f"{EVERY_KIND} (elastic)": _fit({"none": 1.0, "modes": 0.50}, left_out=0.10),
            f"{EVERY_KIND} (viscoelastic)": _fit({"none": 1.0, "modes": 0.45}, left_out=0.20)}
    choice = choose({"scenes": {"a": {"rows": rows}}})
    assert choice["scores"]["modes (viscoelastic)"] == pytest.approx(0.65)
    assert choice["chosen"] == "modes (elastic)"
    rows[f"{EVERY_KIND} (viscoelastic)"] = _fit({"none": 1.0, "modes": 0.403}, left_out=0.2)
    assert choose({"scenes": {"a": {"rows": rows}}})["chosen"] == "modes (elastic)"  # tie
    rows[f"{EVERY_KIND} (viscoelastic)"] = _fit({"none": 1.0, "modes": 0.30}, left_out=0.2)
    assert choose({"scenes": {"a": {"rows": rows}}})["chosen"] == "modes (viscoelastic)"
