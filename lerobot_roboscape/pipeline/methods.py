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
# The guards against a policy that games the world model (issue 49), each a run of PPO in the world model, judged
# by the simulator success of its checkpoints (OOD), not by its own return.
RL_WORLD_MODEL_KL, RL_WORLD_MODEL_ENSEMBLE, RL_WORLD_MODEL_BRANCHED, RL_WORLD_MODEL_REFRESH = (
    "RL w. World Model, KL to SFT",
    "RL w. World Model, ensemble disagreement",
    "RL w. World Model, branched short rollouts",
    "RL w. World Model, done refreshed in the simulator",  # uses simulator rollouts: its own row
)
LEVERS = {
    "kl": RL_WORLD_MODEL_KL,
    "ensemble": RL_WORLD_MODEL_ENSEMBLE,
    "branched": RL_WORLD_MODEL_BRANCHED,
    "refresh": RL_WORLD_MODEL_REFRESH,
}
OOD_ONLY = (*REWARD_ABLATION, *LEVERS.values())  # the methods evaluated out of domain only
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
        RL_WORLD_MODEL_KL: "ppo_world_model_kl",
        RL_WORLD_MODEL_ENSEMBLE: "ppo_world_model_ensemble",
        RL_WORLD_MODEL_BRANCHED: "ppo_world_model_branched",
        RL_WORLD_MODEL_REFRESH: "ppo_world_model_done_refresh",
    }[method]


# The claim's protocols. "paper": the policy's SFT sees the demonstrations of the initial scene only (and PPO in the
# simulator's one-scene baseline runs there), while PPO in the world model starts in every scene the world model
# learned (section 3.2). "all_scenes": SFT on every training scene, which leaves RL less room.
PAPER_PROTOCOL, ALL_SCENES_PROTOCOL = "paper", "all_scenes"
PROTOCOLS = (PAPER_PROTOCOL, ALL_SCENES_PROTOCOL)


def initial_scene() -> str:
    """The one IND scene of the one-scene methods (SFT under the paper's protocol, PPO in one simulator scene)."""
    return select_scenes("ind")[0].id
