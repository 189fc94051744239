"""A quiet console (issue 102): the warnings a user can do nothing about are said once."""

import logging

import torch
from accelerate import PartialState
from accelerate.utils.other import clean_state_dict_for_safetensors

import lerobot_roboscape.training.loop  # noqa: F401  (says Accelerate's tied-weights warning once)
from lerobot_roboscape.io.console import say_once


def test_each_distinct_message_once_without_a_marker(caplog):
    say_once("roboscape.test.distinct")
    logger = logging.getLogger("roboscape.test.distinct")
    with caplog.at_level(logging.WARNING, logger="roboscape.test.distinct"):
        for episode in (1, 2, 1, 2, 3):
            logger.warning("episode %d: no goal", episode)
    assert [r.getMessage() for r in caplog.records] == [
        "episode 1: no goal",
        "episode 2: no goal",
        "episode 3: no goal",
    ]


def test_a_warning_said_once_lets_other_messages_through(caplog):
    say_once("roboscape.test.console", "same old")
    logger = logging.getLogger("roboscape.test.console")
    with caplog.at_level(logging.WARNING, logger="roboscape.test.console"):
        for _ in range(3):
            logger.warning("[RANK 0] same old thing")
            logger.warning("something new")
    assert [r.getMessage() for r in caplog.records] == ["[RANK 0] same old thing"] + ["something new"] * 3


def test_accelerate_says_it_removed_a_tied_tensor_once_per_process(caplog):
    PartialState(cpu=True)  # Accelerate's logging needs its state, as in a training run
    weight = torch.zeros(4, 4)
    with caplog.at_level(logging.WARNING, logger="accelerate.utils.other"):
        for _ in range(3):  # three checkpoints of a model whose head shares its embedding's weight
            clean_state_dict_for_safetensors({"embed.weight": weight, "head.weight": weight})
    removed = [r for r in caplog.records if r.getMessage().startswith("Removed shared tensor")]
    assert len(removed) <= 1  # 0 where an earlier test of this process saved a tied model first
