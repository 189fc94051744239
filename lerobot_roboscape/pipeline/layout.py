"""Where the stages of a run write: their folders under output_dir (the reports and the experiment read them
there)."""

from pathlib import Path
from typing import NamedTuple

from lerobot_roboscape.pipeline.methods import ALL_SCENES_PROTOCOL, PROTOCOLS, Method

DEMOS_DIR = "datasets/roboscape_demos"
DEMOS_REPO_ID = "local/roboscape_demos"
INITIAL_SCENE_DIR = "datasets/roboscape_sft_initial"  # the paper protocol's SFT demonstrations
INITIAL_SCENE_REPO_ID = "local/roboscape_sft_initial"
HELDOUT_DIR = "datasets/roboscape_heldout"
VALIDATION_DIR = "datasets/roboscape_validation"
CONTROL_DIR = "datasets/roboscape_controllability"
CONTROL_IND_DIR = "datasets/roboscape_controllability_ind"
EXPLORE_DIR = "datasets/roboscape_explore"
EXPLORE_REPO_ID = "local/roboscape_explore"
DONE_REPORT_DIR = "done_report"
DONE_REPORT_IND_DIR = "done_report_ind"  # on the validation episodes the threshold was not chosen on (IND)
CONVERTED_DIR = "datasets/maniskill_converted"
TRAJECTORIES_DIR = "maniskill_trajectories"
TOKENIZER_DIR = "tokenizer"
TOKENIZER_REPORT_DIR = "tokenizer_report"
TOKEN_CACHE_DIR = "token_cache"
FIDELITY_DIR = "fidelity"
FIDELITY_IND_DIR = "fidelity_ind"  # the same report from new starts of the training scenes
REWARD_REPORT_DIR = "reward_report"
TABLES_DIR = "tables"
GOAL_FILE = "rl/text_model_goals.safetensors"
RL_DIR = "rl"
EVAL_DIR = "eval"
CURVE_DIR, REPLAY_DIR = "curve", "replay"  # the claim experiment's, in a protocol's folder


def fidelity_dir(domain: str) -> str:
    """The action model's fidelity report from new starts of its training scenes ("ind") or OOD starts ("ood")."""
    if domain not in ("ind", "ood"):
        raise ValueError(f"domain must be 'ind' or 'ood', got {domain!r}")
    return FIDELITY_IND_DIR if domain == "ind" else FIDELITY_DIR


def protocol_dir(protocol: str) -> str:
    """The folder of a claim protocol's policy runs (SFT, PPO, evaluations): the all-scene protocol's are the
    pipeline's own, in output_dir itself."""
    if protocol not in PROTOCOLS:
        raise ValueError(f"protocol must be one of {PROTOCOLS}, got {protocol!r}")
    return "" if protocol == ALL_SCENES_PROTOCOL else f"protocol_{protocol}"


def world_model_dir(control: str) -> str:
    return f"world_model_{control}"


class WorldModelPaths(NamedTuple):
    """A run's two world models (pretrained_model folders)."""

    action: Path
    text: Path

    def items(self):
        """(control, folder) of each: the control is the one the model was trained with (`--wm.control`)."""
        return self._asdict().items()


def reward_model_dir(kind: str) -> str:
    return f"reward_{kind}"


def sft_dir(policy: str) -> str:
    return f"sft_{policy.removeprefix('roboscape_')}"


def lerobot_eval_dir(policy: str) -> str:
    return f"eval_{policy}_roboscape_wm"


def rl_dir(policy: str, method: str) -> Path:
    return Path(RL_DIR) / policy / Method.named(method).tag


def replay_dir(method: str) -> Path:
    """The replay in the simulator of a run in the world model's rollouts."""
    return Path(REPLAY_DIR) / Method.named(method).tag


def eval_dir(policy: str, method: str) -> Path:
    """The simulator evaluation of one checkpoint (a folder per split inside)."""
    return Path(EVAL_DIR) / policy / Method.named(method).tag
