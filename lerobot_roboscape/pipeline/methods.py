"""The methods a policy is trained by, as Table 1 names them, the reward models beside the world model's own
reward, and the methods' names in folders and Hub repos."""

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
