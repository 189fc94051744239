"""PPO's settings (`roboscape-ppo`'s flags): the run, the env, the optimisation, and each policy type's defaults."""

from dataclasses import dataclass, field
from pathlib import Path

from lerobot.envs.configs import EnvConfig

from lerobot_roboscape.envs.configs import RoboscapeWorldModelEnvConfig
from roboscape_core.errors import InvalidInputError

# Per policy type: RL4VLA's settings for OpenVLA; ours for the MLP (its learning rate measured at the bench scale).
PPO_DEFAULTS = {
    "openvla": dict(
        policy_lr=1e-4,
        value_lr=3e-3,
        update_epochs=1,
        minibatch_size=8,
        grad_accum_steps=20,
        max_grad_norm=10.0,
        value_loss="huber",
        vf_coef=1.0,
        critic_warmup_iterations=5,
    ),
    "roboscape_mlp": dict(
        # Its Gaussian over a chunk of 4 actions is narrow (std 0.22): at 3e-4 or 1e-4 one update moved the
        # policy 0.2-20 nats (approximate KL) and PPO in the simulator lost SFT's success; 3e-5 moves it ~0.03
        # (docs/results/bench/ppo_learning_rate.md).
        policy_lr=3e-5,
        value_lr=1e-3,
        update_epochs=4,
        minibatch_size=64,
        grad_accum_steps=1,
        max_grad_norm=0.5,
        value_loss="mse",
        vf_coef=0.5,
        critic_warmup_iterations=2,
    ),
}


# Parallel episodes a PPO iteration plays: the bench experiment's 8 on 2 CPU cores (docs/results/bench/report.md); the
# pipeline's scales and roboscape-ppo share it, a scale overrides it where it sizes PPO (smoke, GPU, paper).
NUM_ENVS = 8


@dataclass
class PPOConfig:
    """Args:
    policy_path: the policy to start from (an SFT checkpoint's pretrained_model directory or a Hub repo id).
    env: the env to train in (`--env.type=roboscape_wm` or `roboscape_maniskill`, with its options).
    output_dir: checkpoints (output_dir/checkpoints/NNNNNNNN/pretrained_model), logs and videos.
    num_envs: parallel episodes per iteration, over all processes.
    iterations: PPO iterations (one episode per env each).
    time_budget_s: stop after the iteration that brings the run's time (rollouts and updates, over resumes) to
        this many seconds, if that comes before `iterations`: compares RL in two envs at equal wall-clock.
    gamma: discount.
    gae_lambda: GAE lambda.
    clip_coef: policy ratio clipping.
    value_clip_coef: value clipping around the rollout's values (null: none, the default). A critic that starts
        far from its targets (a fresh value head after SFT) would move only this far per iteration: clipping keeps
        it frozen, and it did not help PPO in Andrychowicz et al. 2021 ("What matters in on-policy RL").
    ent_coef: entropy bonus.
    target_kl: stop the iteration's update at the first minibatch whose approximate KL divergence from the rollout's
        policy exceeds this (null: never; as Stable-Baselines3). A narrow Gaussian over a chunk of actions moves
        far in KL for a small step of its mean.
    kl_coef: weight of a penalty on the policy's KL divergence from the policy PPO started from (`policy_path`,
        the SFT checkpoint), estimated on the rollout's samples (Schulman's k3 estimator: non-negative, unbiased).
        It keeps PPO where the SFT policy, and so the world model's data, went (issue 49); 0: none. A second copy
        of the starting policy is held, frozen.
    init_std: the std of the policy's Gaussian when PPO starts (a fresh run, not a resume), in normalised action units;
        null: the checkpoint's. SFT fits only the Gaussian's mean, so the std it leaves is its initial value, not
        one the demonstrations chose (policies that sample tokens, OpenVLA, have none).
    advantage: "gae" (a critic's, the default) or "group" (GRPO's, as SimpleVLA-RL and RLinf: `group_size` episodes
        start from one scene and initial state, and each episode's advantage is its success minus its group's mean
        success over their std, the same for all its decisions; no critic, no reward scaling).
    group_size: episodes per start with advantage="group" (num_envs must be a multiple of it times the number of
        task families).
    keep_mixed_groups: with advantage="group", train only on groups whose episodes neither all succeeded nor all
        failed (the others carry no signal; SimpleVLA-RL's dynamic sampling).
    norm_adv: normalise advantages over the iteration's samples.
    normalize_reward: divide rewards by the running standard deviation of the discounted return (as gymnasium's
        NormalizeReward in CleanRL), so the critic's targets stay near unit scale whatever the reward's weights.
    critic_warmup_iterations: first iterations that train the value head only; null: the policy type's default.
    policy_lr: learning rate of the policy's parameters (LoRA for OpenVLA); null: the policy type's default.
    value_lr: learning rate of the value head; null: default.
    update_epochs: passes over the iteration's samples; null: default.
    minibatch_size: samples per gradient computation; null: default.
    grad_accum_steps: minibatches per optimiser step; null: default.
    max_grad_norm: gradient-norm clipping, of the policy's and the value head's gradients separately; null: default.
    value_loss: "mse" (half the squared error) or "huber" (Huber with `huber_delta`, as RL4VLA); null: default.
    huber_delta: the Huber loss's delta.
    vf_coef: value loss coefficient; null: default.
    device: "auto" (cuda when present), "cpu" or "cuda"; Accelerate picks the GPU of each process.
    mixed_precision: "auto" (bf16 on GPUs that support it), "bf16" or "no".
    seed: seed of the env resets, the action sampling and the minibatches (one stream per iteration).
    save_freq: iterations between checkpoints (the last iteration always saves).
    video_freq: iterations between rollout videos (0: none).
    resume: continue from the last checkpoint in output_dir.
    wandb: also log to Weights & Biases (when installed).
    """

    policy_path: str = ""
    env: EnvConfig = field(default_factory=RoboscapeWorldModelEnvConfig)
    output_dir: Path = Path("outputs/ppo")
    num_envs: int = NUM_ENVS
    iterations: int = 100
    time_budget_s: float | None = None
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_coef: float = 0.2
    value_clip_coef: float | None = None
    ent_coef: float = 0.0
    target_kl: float | None = None
    kl_coef: float = 0.0
    init_std: float | None = None
    advantage: str = "gae"
    group_size: int = 4
    keep_mixed_groups: bool = True
    norm_adv: bool = True
    normalize_reward: bool = True
    critic_warmup_iterations: int | None = None
    policy_lr: float | None = None
    value_lr: float | None = None
    update_epochs: int | None = None
    minibatch_size: int | None = None
    grad_accum_steps: int | None = None
    max_grad_norm: float | None = None
    value_loss: str | None = None
    huber_delta: float = 10.0
    vf_coef: float | None = None
    device: str = "auto"
    mixed_precision: str = "auto"
    seed: int = 0
    save_freq: int = 10
    video_freq: int = 0
    resume: bool = False
    wandb: bool = False

    def __post_init__(self):
        if not self.policy_path:
            raise InvalidInputError("--policy_path is required: the SFT checkpoint (or Hub repo id) PPO starts from")
        if self.num_envs < 1 or self.iterations < 1 or self.save_freq < 1:
            raise InvalidInputError(
                f"num_envs, iterations and save_freq must be >= 1, got {self.num_envs}, "
                f"{self.iterations}, {self.save_freq}"
            )
        if self.kl_coef < 0:
            raise InvalidInputError(f"kl_coef must be >= 0, got {self.kl_coef}")
        if self.init_std is not None and self.init_std <= 0:
            raise InvalidInputError(f"init_std must be > 0 or null (the checkpoint's), got {self.init_std}")
        if self.advantage not in ("gae", "group"):
            raise InvalidInputError(f"advantage must be gae or group, got {self.advantage!r}")
        if self.advantage == "group" and (self.group_size < 2 or self.num_envs % self.group_size):
            raise InvalidInputError(
                f"advantage=group needs group_size >= 2 dividing num_envs, got group_size={self.group_size} "
                f"and num_envs={self.num_envs}"
            )
        if self.value_loss not in (None, "mse", "huber"):
            raise InvalidInputError(f"value_loss must be mse or huber, got {self.value_loss!r}")
        self.output_dir = Path(self.output_dir)

    def with_policy_defaults(self, policy_type: str) -> "PPOConfig":
        """Fill the fields left null with the defaults of `policy_type`."""
        if policy_type not in PPO_DEFAULTS:
            unset = [name for name in PPO_DEFAULTS["roboscape_mlp"] if getattr(self, name) is None]
            if unset:
                raise InvalidInputError(
                    f"PPO has no defaults for policy type {policy_type!r} (it knows "
                    f"{sorted(PPO_DEFAULTS)}): set {', '.join(f'--{n}' for n in unset)}"
                )
            return self
        for name, value in PPO_DEFAULTS[policy_type].items():
            if getattr(self, name) is None:
                setattr(self, name, value)
        return self
