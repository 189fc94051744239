import numpy as np

from lerobot_roboscape.reward.done_report import choose_threshold, confusion, roc_auc


def test_threshold_separates_validation_successes_from_failures():
    scores = np.array([0.1, 0.3, 0.35, 0.8, 0.9])
    success = np.array([False, False, False, True, True])
    theta = choose_threshold(scores, success)
    assert 0.35 < theta <= 0.8
    assert confusion(scores, success, theta) == {
        "success_called_done": 2,
        "success_missed": 0,
        "failed_called_done": 0,
        "failed_not_done": 3,
        "failed_called_done_rate": 0.0,
    }


def test_threshold_prefers_fewer_false_alarms_among_equals():
    # 0.25 (all successes, half the failures) and 0.75 (half the successes, no failure) are equally good.
    scores = np.array([0.1, 0.4, 0.6, 0.9])
    success = np.array([False, True, False, True])
    assert choose_threshold(scores, success) == 0.75


def test_roc_auc_needs_both_kinds():
    assert roc_auc(np.array([0.1, 0.9]), np.array([0, 1])) == 1.0
    assert roc_auc(np.array([0.1, 0.9]), np.array([1, 1])) is None
