"""The methods a policy is trained by, as Table 1 names them, the protocols they are compared under, the reward
models beside the world model's own reward, and the methods' names in folders and Hub repos."""

from lerobot_roboscape.tasks import select_scenes


class Method(str):
    """A method a policy is trained by. It is Table 1's name, so results keyed by it read and write as plain
    strings; `tag` names it in folders and Hub repos; `variant` sets a variant of PPO in the world model apart
    (the reward ablation's and the levers': run, and evaluated, out of domain only). Every method made is found
    again by its name (`Method.named`), so a name read back from a results file gives back the method."""

    tag: str
    variant: str
    _known: dict[str, "Method"] = {}

    def __new__(cls, label: str, tag: str, variant: str = "") -> "Method":
        if (known := cls._known.get(label)) is not None:
            if (known.tag, known.variant) != (tag, variant):
                raise ValueError(f"two methods are named {label!r}")
            return known  # the same method made again (unpickled): one object per method
        method = super().__new__(cls, label)
        method.tag, method.variant = tag, variant
        cls._known[label] = method
        return method

    def __reduce__(self):  # copied or unpickled (also in a process that never made it): the same method
        return Method, (str(self), self.tag, self.variant)

    @property
    def ood_only(self) -> bool:
        return bool(self.variant)

    @classmethod
    def named(cls, label: str) -> "Method":
        if label not in cls._known:
            raise KeyError(f"no method is named {label!r}; known: {list(cls._known)}")
        return cls._known[label]


SFT = Method("Supervised finetune", "sft")
RL_MANISKILL_ONE_SCENE = Method("RL w. ManiSkill (one scene)", "ppo_maniskill_one_scene")
RL_MANISKILL = Method("RL w. ManiSkill", "ppo_maniskill")
RL_WORLD_MODEL = Method("RL w. World Model", "ppo_world_model")


def world_model_variant(variant: str, tag: str) -> Method:
    """A variant of PPO in the world model (a reward term alone, a lever), named as Table 1's rows name it."""
    return Method(f"{RL_WORLD_MODEL}, {variant}", f"{RL_WORLD_MODEL.tag}_{tag}", variant)


# The reward ablation (issue 29): PPO in the world model paid one of its two reward terms.
RL_WORLD_MODEL_SPARSE = world_model_variant("sparse reward only", "sparse")
RL_WORLD_MODEL_DENSE = world_model_variant("dense reward only", "dense")
REWARD_ABLATION = (RL_WORLD_MODEL_SPARSE, RL_WORLD_MODEL_DENSE)
POLICIES = ("roboscape_mlp", "openvla")
REWARD_BASELINES = ("embedding", "proxy")
SUCCESS_CLASSIFIER = "success"  # the reward model kind that is a success classifier (a done source)


# The claim's protocols. "paper": the policy's SFT sees the demonstrations of the initial scene only (and PPO in the
# simulator's one-scene baseline runs there), while PPO in the world model starts in every scene the world model
# learned (section 3.2). "all_scenes": SFT on every training scene, which leaves RL less room.
PAPER_PROTOCOL, ALL_SCENES_PROTOCOL = "paper", "all_scenes"
PROTOCOLS = (PAPER_PROTOCOL, ALL_SCENES_PROTOCOL)


def initial_scene() -> str:
    """The one IND scene of the one-scene methods (SFT under the paper's protocol, PPO in one simulator scene)."""
    return select_scenes("ind")[0].id
