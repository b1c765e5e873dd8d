"""Forward selection of model terms by cross-validation (calibration.compliance_fit.select_terms,
issue 25 case 5): a combination whose cross-validated gain passes the threshold is found even
when no single term passes it. The scores are the WAM's measured 5-fold CV figures (mm), which
single-term selection left rigid."""

from __future__ import annotations

import pytest

from calibration.compliance_fit import MIN_CV_GAIN, select_terms

# the 7-axis WAM, 5-fold CV RMS (mm) of the rigid model and with compliance on the named joints
WAM = {(): 2.405, ("j2",): 2.378, ("j3",): 2.349, ("j2", "j3"): 2.271, ("j4",): 2.404, ("j2", "j4"): 2.377}


def _score(table, calls):
    def score(terms):
        calls.append(terms)
        return table.get(terms, table[()] * 1.001)  # a set not in the table: no gain

    return score


def test_a_pair_that_passes_is_found_when_no_single_term_does():
    calls = []
    chosen = select_terms(("j2", "j3", "j4"), _score(WAM, calls), MIN_CV_GAIN)
    assert chosen == ("j2", "j3")
    assert 1 - WAM[("j2", "j3")] / WAM[()] > MIN_CV_GAIN > 1 - WAM[("j3",)] / WAM[()]
    # at the stated cost: the rigid model, 3 singles and 3 pairs; then from the pair, the one
    # remaining single (no pair or "all the rest" of one term)
    assert len(set(calls)) == 1 + 3 + 3 + 1


def test_all_remaining_terms_together_when_no_pair_passes():
    table = {(): 1.0, ("a", "b", "c", "d"): 0.9}  # each alone and each pair gains nothing
    assert select_terms(("a", "b", "c", "d"), _score(table, []), MIN_CV_GAIN) == ("a", "b", "c", "d")


@pytest.mark.parametrize(
    "table,expected",
    [
        ({(): 1.0, ("a",): 0.9, ("a", "b"): 0.8}, ("a", "b")),  # one at a time, as before
        ({(): 1.0, ("a",): 0.97, ("b",): 0.98, ("a", "b"): 0.96}, ()),  # nothing passes: rigid
    ],
)
def test_single_steps_and_no_gain(table, expected):
    assert select_terms(("a", "b"), _score(table, []), MIN_CV_GAIN) == expected
