"""Which world-model rollouts the replay sends to the simulator (`picked`): the world model's successes first,
capped and spread over the rollouts, then as many of its failures."""

import numpy as np

from lerobot_roboscape.experiments.replay import picked


def test_successes_come_first_spread_over_the_rollouts_then_as_many_failures():
    success = np.zeros(64, dtype=bool)
    success[[3, 10, 20, 30, 40, 50]] = True
    chosen = picked(success, per_outcome=3)
    assert chosen[:3] == [3, 20, 50]  # the first, a middle and the last success, not the first three
    assert len(chosen) == 6 and not success[chosen[3:]].any() and chosen[3] == 0 and chosen[-1] == 63


def test_fewer_successes_than_asked_are_all_replayed_and_none_is_repeated():
    success = np.array([False, True, False, False])
    assert picked(success, per_outcome=16) == [1, 0, 2, 3]
    assert picked(np.zeros(5, dtype=bool), per_outcome=2) == [0, 4]
