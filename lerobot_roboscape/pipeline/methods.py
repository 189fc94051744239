"""The methods a policy is trained by, as Table 1 names them, the protocols they are compared under, the reward
models beside the world model's own reward, and the methods' names in folders and Hub repos."""

from lerobot_roboscape.tasks import select_scenes

SFT, RL_MANISKILL_ONE_SCENE, RL_MANISKILL, RL_WORLD_MODEL = (
    "Supervised finetune",
    "RL w. ManiSkill (one scene)",
    "RL w. ManiSkill",
    "RL w. World Model",
)
# The reward ablation (issue 29): PPO in the world model paid one of its two reward terms; evaluated OOD only.
RL_WORLD_MODEL_SPARSE, RL_WORLD_MODEL_DENSE = (
    "RL w. World Model, sparse reward only",
    "RL w. World Model, dense reward only",
)
REWARD_ABLATION = (RL_WORLD_MODEL_SPARSE, RL_WORLD_MODEL_DENSE)
POLICIES = ("roboscape_mlp", "openvla")
REWARD_BASELINES = ("embedding", "proxy")
SUCCESS_CLASSIFIER = "success"  # the reward model kind that is a success classifier (a done source)


def method_tag(method: str) -> str:
    """The method's name in folders and Hub repos."""
    return {
        SFT: "sft",
        RL_WORLD_MODEL: "ppo_world_model",
        RL_MANISKILL: "ppo_maniskill",
        RL_MANISKILL_ONE_SCENE: "ppo_maniskill_one_scene",
        RL_WORLD_MODEL_SPARSE: "ppo_world_model_sparse",
        RL_WORLD_MODEL_DENSE: "ppo_world_model_dense",
    }[method]


# The claim's protocols. "paper": the policy's SFT sees the demonstrations of the initial scene only (and PPO in the
# simulator's one-scene baseline runs there), while PPO in the world model starts in every scene the world model
# learned (section 3.2). "all_scenes": SFT on every training scene, which leaves RL less room.
PAPER_PROTOCOL, ALL_SCENES_PROTOCOL = "paper", "all_scenes"
PROTOCOLS = (PAPER_PROTOCOL, ALL_SCENES_PROTOCOL)


def initial_scene() -> str:
    """The one IND scene of the one-scene methods (SFT under the paper's protocol, PPO in one simulator scene)."""
    return select_scenes("ind")[0].id
