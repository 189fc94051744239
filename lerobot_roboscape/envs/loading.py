"""What `roboscape_wm` loads: the tokenizer and the world models (local directories or Hub repo ids, or one world
models repo that names them all), the baseline reward models and the goal similarity, each once per process."""

from dataclasses import dataclass
from functools import lru_cache

from lerobot_roboscape.hub.pull import pull_world_models, snapshot
from lerobot_roboscape.reward.baselines import RewardModel
from lerobot_roboscape.reward.world_model_reward import WorldModelReward
from lerobot_roboscape.tokenizer.modeling_tokenizer import VisualTokenizer
from lerobot_roboscape.tokenizer.similarity import load_similarity
from lerobot_roboscape.world_model.modeling_world_model import STWorldModel
from roboscape_core.errors import InvalidInputError, MissingInputError


def load_pretrained(cls, ref: str, what: str, command: str):
    """`cls.from_pretrained` of a local directory or a Hub repo id, with an error naming what is missing."""
    path = snapshot(ref, what, f"train one with `{command}`")
    if not (path / "config.json").is_file():
        raise MissingInputError(
            f"no {what} at {ref} (config.json missing); train one with `{command}` or give a Hub repo id"
        )
    return cls.from_pretrained(str(path))


def model_refs(config) -> tuple[str, str, str | None, str]:
    """Tokenizer, action model, text model (None when unused) and dataset repo id of a `roboscape_wm` config:
    from its `world_models` repo, or given one by one."""
    uses_text = config.goal_source == "text_model"
    if config.world_models:
        bundle = pull_world_models(config.world_models)
        return (
            str(bundle.tokenizer),
            str(bundle.action_world_model),
            str(bundle.text_world_model) if uses_text else None,
            config.dataset_repo_id or bundle.dataset_repo_id,
        )
    if not config.dataset_repo_id and not config.starts_file:
        raise InvalidInputError(
            "roboscape_wm needs dataset_repo_id (the dataset of the initial frames), world_models (a repo that "
            "names it) or starts_file (its starts, saved)"
        )
    return (
        config.tokenizer,
        config.action_world_model,
        config.text_world_model if uses_text else None,
        config.dataset_repo_id,
    )


@lru_cache(maxsize=8)
def load_models(tokenizer: str, action_model: str, text_model: str | None, device: str):
    """Tokenizer and world models, loaded once per process (local directories or Hub repo ids)."""
    loaded = [
        load_pretrained(VisualTokenizer, tokenizer, "tokenizer", "roboscape-train-tokenizer"),
        load_pretrained(STWorldModel, action_model, "action world model", "roboscape-train-wm --wm.control=action"),
        load_pretrained(STWorldModel, text_model, "text world model", "roboscape-train-wm --wm.control=text")
        if text_model
        else None,
    ]
    return tuple(m.to(device).eval() if m is not None else None for m in loaded)


def load_ensemble(refs, action_model: STWorldModel, device: str) -> tuple[STWorldModel, ...]:
    """The action world models of an ensemble beside `action_model`, each checked to predict the same frames from
    the same actions."""
    members = _ensemble_members(tuple(refs), device)
    ours = action_model.config
    layout = lambda c: (c.control, c.frame_skip, c.tokens_per_frame, c.vocab_size, c.action_dim)  # noqa: E731
    for ref, member in zip(refs, members, strict=True):
        if layout(member.config) != layout(ours):
            raise InvalidInputError(
                f"ensemble member {ref} (control, frame_skip, tokens per frame, vocabulary, action_dim = "
                f"{layout(member.config)}) does not match the action world model {layout(ours)}"
            )
    return members


@lru_cache(maxsize=4)
def _ensemble_members(refs: tuple[str, ...], device: str) -> tuple[STWorldModel, ...]:
    """The action world models of an ensemble, loaded once per process."""
    command = "roboscape-train-wm --wm.control=action --train.seed=<another seed>"
    return tuple(load_pretrained(STWorldModel, ref, "ensemble member", command).to(device).eval() for ref in refs)


@lru_cache(maxsize=4)
def load_reward_model(ref: str | None, device: str) -> RewardModel:
    if not ref:
        raise InvalidInputError(
            "reward_type embedding/proxy needs reward_model (train one with roboscape-train-reward)"
        )
    return load_pretrained(RewardModel, ref, "reward model", "roboscape-train-reward").to(device).eval()


@lru_cache(maxsize=4)
def load_reward_distance(kind: str, tokenizer: VisualTokenizer, weights: str | None, allow_random: bool, device: str):
    return load_similarity(kind, tokenizer, tokenizer.config.lpips_net, weights, allow_random).to(device)


@dataclass(frozen=True)
class EnvRewards:
    """What pays roboscape_wm's episodes and what calls them done: the world models' own reward (`paid`, with its
    description), or a baseline reward model; the done head, or a success classifier."""

    paid: WorldModelReward
    description: str
    model: RewardModel | None
    classifier: RewardModel | None


def load_rewards(config, tokenizer: VisualTokenizer, device: str) -> EnvRewards:
    """The rewards a `RoboscapeWorldModelEnvConfig` asks for, each checked to be the kind it is used as."""
    c = config
    distance = load_reward_distance(
        config.similarity, tokenizer, config.lpips_weights, config.allow_random_lpips, device
    )
    paid = WorldModelReward(
        distance, alpha=config.alpha, beta=config.beta, theta_sps=config.theta_sps, sparse_value=config.sparse_reward
    )
    description = (
        f"world models: {config.alpha} x {config.sparse_reward} while done >= {config.theta_sps} + {config.beta} "
        f"x (1 - {distance.name} distance to the goal frame)"
    ) + (f" - {config.disagreement_penalty} x the ensemble's disagreement" if config.disagreement_penalty else "")
    model = None
    if config.reward_type != "world_model":
        model = load_reward_model(config.reward_model, device)
        if model.config.kind != config.reward_type:
            raise InvalidInputError(
                f"{c.reward_model} is a {model.config.kind} reward model, but reward_type is {c.reward_type!r}"
            )
    classifier = None
    if config.done_source == "classifier":
        classifier = load_reward_model(config.success_classifier, device)
        if classifier.config.kind != "success":
            raise InvalidInputError(
                f"{config.success_classifier} is a {classifier.config.kind} reward model, not a success classifier "
                "(roboscape-train-reward --reward.kind=success)"
            )
    return EnvRewards(paid, description, model, classifier)
