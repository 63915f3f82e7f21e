"""The one failed-pick memory, under the tool check's rule and the oracle's (known points, normals and outcomes)."""

from __future__ import annotations

import numpy as np

from policies.failed_picks import FailedPicks

UP, TILTED = np.array([0.0, 0.0, 1.0]), np.array([0.0, np.sin(np.radians(30)), np.cos(np.radians(30))])


def test_the_tool_checks_rule_keys_a_failure_to_the_contact_and_forgets_it_on_a_success():
    failed = FailedPicks()
    offered = np.array([0.1, 0.0, 0.2])
    assert failed.note({"attempts": 1, "outcome": "dropped", "contacted": True, "contact_point": [0.0, 0.0, 0.2]},
                       offered)
    assert not failed.note({"attempts": 1, "outcome": "dropped"}, offered)  # the same attempt, read once
    assert failed.note({"attempts": 2, "outcome": "unreachable", "contacted": False}, offered)  # never touched
    np.testing.assert_allclose(failed.points, [[0.0, 0.0, 0.2], [0.1, 0.0, 0.2]])
    probes = np.array([[0.0, 0.03, 0.2], [0.0, 0.06, 0.2], [0.05, 0.0, 0.2]])
    assert failed.count_near(probes, 0.05).tolist() == [1, 0, 2]  # within 5 cm of the first, of both
    assert failed.near(probes, 0.0).tolist() == [False] * 3  # radius 0: off
    assert not failed.note({"attempts": 3, "outcome": "success"}, offered)
    assert len(failed.points) == 0


def test_the_oracles_rule_keys_a_failure_to_the_offered_approach_for_the_whole_episode():
    failed = FailedPicks(forget_on_success=False, at_contact=False)
    pick = np.array([0.0, 0.0, 0.2])
    assert failed.note({"attempts": 1, "outcome": "dropped", "contacted": True, "contact_point": [0.3, 0.3, 0.3]},
                       pick, UP)
    np.testing.assert_allclose(failed.points, [pick])  # the offered pick, not the contact
    failed.note({"attempts": 2, "outcome": "success"}, pick, UP)
    assert len(failed.points) == 1  # a success elsewhere leaves it
    # the same point approached along the same normal is the same pick; 30 deg off it, another approach
    both = np.array([pick, pick])
    assert failed.count_near(both, 0.02, np.array([UP, TILTED]), 20.0).tolist() == [1, 0]
    assert failed.count_near(both, 0.02, np.array([UP, TILTED]), 40.0).tolist() == [1, 1]
    assert failed.count_near(both + [0.03, 0.0, 0.0], 0.02, np.array([UP, UP]), 20.0).tolist() == [0, 0]
    failed.clear()
    assert len(failed.points) == 0 and failed.note({"attempts": 1, "outcome": "dropped"}, pick, UP)  # a new episode


def test_a_failure_without_an_offered_pick_or_outcome_is_not_recorded():
    failed = FailedPicks()
    assert not failed.note(None, np.zeros(3))
    assert not failed.note({"attempts": 1}, np.zeros(3))  # the reset's info: no attempt yet
    assert not failed.note({"attempts": 1, "outcome": "dropped", "contacted": False}, None)
    assert failed.count_near(np.zeros((2, 3)), 0.05).tolist() == [0, 0]


def test_each_failure_keeps_its_callers_tag_and_forgets_it_with_the_failure():
    """The oracle tags a failure with the parcel it aimed at; the tags follow the failures, one each."""
    kept = FailedPicks(forget_on_success=False, at_contact=False)
    assert kept.note({"attempts": 1, "outcome": "dropped"}, np.zeros(3), UP, tag=(7, np.ones(3)))
    assert kept.note({"attempts": 2, "outcome": "no_seal"}, np.ones(3), UP)  # untagged
    assert not kept.note({"attempts": 3, "outcome": "success"}, np.ones(3), UP, tag="not a failure")
    assert [t if t is None else t[0] for t in kept.tags] == [7, None]
    forgetful = FailedPicks()
    forgetful.note({"attempts": 1, "outcome": "dropped"}, np.zeros(3), tag="a")
    forgetful.note({"attempts": 2, "outcome": "success"}, np.zeros(3), tag="b")
    assert forgetful.tags == [] and len(forgetful.points) == 0
    forgetful.note({"attempts": 3, "outcome": "dropped"}, np.zeros(3), tag="c")
    forgetful.clear()
    assert forgetful.tags == []
