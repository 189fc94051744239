"""The world models' targets (issue 28, 47, 70): controllability, open-loop fidelity and the arm, IND and OOD; the
done signal, the goals and the reward on held-out OOD episodes; the agreement with the simulator. Each reads the
stage's report through that stage's readings."""

from lerobot_roboscape.envs.reward_readings import RewardReadings
from lerobot_roboscape.evaluation.agreement_readings import Ladder
from lerobot_roboscape.io.templates import number
from lerobot_roboscape.pipeline.methods import REWARD_BASELINES
from lerobot_roboscape.pipeline.report.target_row import target_row
from lerobot_roboscape.reward.done_readings import DoneReport
from lerobot_roboscape.training.loop import TrainingTime
from lerobot_roboscape.world_model.measures.fidelity_readings import ArmReading, FidelityReadings

# The world models', done and reward, on held-out OOD episodes with failures (issue 28).
WM_PSNR_GAP_DB = 3.0  # open-loop PSNR over the fidelity report's horizon (16 control steps), below the tokenizer's
WM_PSNR_GAP_IND_DB = 2.0  # the same, from new starts of the training scenes (issue 47)
RETRIEVAL = 0.9  # rollouts nearer their own real future than the K - 1 others' (measures/controllability.py), IND
RETRIEVAL_OOD = 0.75  # from starts in scenes the model never saw (issue 47)
ACTION_GAIN_DB = 3.0  # Genie's delta-PSNR: true actions against another episode's
# The arm (issue 70), over the same steps: the predicted state's TCP position error as a share of the distance the
# real TCP moved (median), retrieval by state, the arm region's PSNR below the tokenizer's, the motion ratio.
TCP_ERROR_SHARE = 0.15
RETRIEVAL_STATE = 0.95
ARM_PSNR_GAP_DB = 3.0
MOTION_RATIO = (0.7, 1.3)
DONE_ROC_AUC_TEACHER_FORCED = 0.95
DONE_ROC_AUC_OPEN_LOOP = 0.9
DONE_FAILED_CALLED_DONE = 0.1  # share of failed episodes the done signal calls done, at the chosen threshold
DONE_SUCCESS_CALLED_DONE = 0.7  # share of successful episodes it calls done, open loop
DONE_FAILED_CALLED_DONE_IND = 0.2  # in domain, on its own set of episodes (issue 70)
ACTION_WM_TRAIN_MINUTES = 60  # the bench action model on 2 CPU cores
GOAL_REACHED = 0.7  # issue 37: from held-out starts, within the family's horizon
GOAL_NEARER_FINAL = 0.9
GOAL_OWN_INSTRUCTION = 0.8  # the real success nearer its own instruction's goal than another family's (issue 37)
REWARD_ROC_AUC = 0.9
AGREEMENT_BALANCED_ACCURACY = 0.8  # per-episode success, world model against simulator, OOD
LADDER_SPEARMAN = 0.9  # the world model's mean return ranking the policies as the simulator's success does
LADDER_RUNGS = 5  # over at least this many policies the simulator tells apart (issue 72)
REWARD_DENSE_ROC_AUC = 0.75  # the dense term alone, on frames generated open loop


# Issue 47: the world model is judged first where RL runs (new initial states of the training scenes), then OOD.
FIDELITY_GOALS = {
    # domain: (words in the target's name, retrieval, open-loop PSNR gap to the tokenizer in dB)
    "ind": ("new starts in the training scenes (IND)", RETRIEVAL, WM_PSNR_GAP_IND_DB),
    "ood": ("held-out OOD starts", RETRIEVAL_OOD, WM_PSNR_GAP_DB),
}


def fidelity_targets(fidelity: "FidelityReadings | dict", domain: str) -> dict:
    """Whether the action model follows its actions and keeps the scene and the arm, from a fidelity report (with
    its controllability reading) on starts of `domain`: retrieval of its own future (whole frame; the object's region
    in the detail), the action gain, open-loop PSNR against the tokenizer's and, OOD, the object's PSNR (an unseen
    object must keep its identity); then the arm's measures where the report has them."""
    fidelity = FidelityReadings.from_json(fidelity)
    where, retrieval_goal, gap = FIDELITY_GOALS[domain]
    steps = f"first {fidelity.horizon} control steps, {where}"
    targets = {}
    control, longer = fidelity.control, fidelity.control_long
    if control and control.whole_frame is not None:
        measures = control.whole_frame
        detail = f"{measures.starts} starts; a model ignoring the actions: "
        detail += f"{control.whole_frame_ignoring_actions.retrieval:.3f}"
        if control.object is not None:
            detail += f"; the object's region: {control.object.retrieval:.3f}"
        if control.likelihood_retrieval is not None:
            detail += f"; from the likelihood of each real future: {control.likelihood_retrieval:.3f}"
        if longer and longer.whole_frame is not None:
            detail += f"; over {fidelity.long_horizon} control steps: {longer.whole_frame.retrieval:.3f}"
        targets[f"action WM retrieval of its own future among 4 action sequences, whole frame, {steps}"] = target_row(
            measures.retrieval, f">= {retrieval_goal}", measures.retrieval >= retrieval_goal, detail
        )
    if control and control.action_gain_db is not None:
        gain = control.action_gain_db
        targets[f"action WM action gain (dB), {steps}"] = target_row(
            gain,
            f">= {ACTION_GAIN_DB:g}",
            gain >= ACTION_GAIN_DB,
            "Genie's delta-PSNR: true actions against the next start's"
            + (f"; over {fidelity.long_horizon} steps: {longer.action_gain_db:.2f}" if longer else ""),
        )
    for measure, label in (("psnr", "open-loop PSNR"), ("object_psnr", "open-loop object PSNR")):
        if measure == "object_psnr" and domain != "ood":
            continue
        prediction = fidelity.mean_over_steps(f"prediction_{measure}")
        reconstruction = fidelity.mean_over_steps(f"reconstruction_{measure}")
        if prediction is None or reconstruction is None:
            continue
        targets[f"action WM {label}, {steps} (dB; tokenizer {reconstruction:.2f})"] = target_row(
            prediction,
            f">= {reconstruction - gap:.2f} (tokenizer - {gap:g})",
            prediction >= reconstruction - gap,
        )
    return targets | (arm_targets(control.arm, steps) if control else {})


def arm_targets(arm: ArmReading, steps: str) -> dict:
    """The arm's targets (issue 70): the predicted state's TCP error and retrieval by state, the arm region's PSNR
    beside the tokenizer's, and the motion ratio (a rollout that stops moving scores well on PSNR)."""
    targets = {}
    if arm.tcp_error_share_of_moved is not None:
        share = arm.tcp_error_share_of_moved
        targets[f"action WM state: TCP error at the last step, share of the distance moved (median), {steps}"] = (
            target_row(share, f"<= {TCP_ERROR_SHARE}", share <= TCP_ERROR_SHARE, f"{arm.tcp_error_cm:.2f} cm")
        )
    if arm.retrieval_state is not None:
        targets[f"action WM retrieval by state among 4 action sequences, {steps}"] = target_row(
            arm.retrieval_state, f">= {RETRIEVAL_STATE}", arm.retrieval_state >= RETRIEVAL_STATE
        )
    if arm.arm_psnr is not None and arm.arm_psnr_tokenizer is not None:
        floor = arm.arm_psnr_tokenizer - ARM_PSNR_GAP_DB
        targets[f"action WM arm region PSNR, {steps} (dB; tokenizer {arm.arm_psnr_tokenizer:.2f})"] = target_row(
            arm.arm_psnr, f">= {floor:.2f} (tokenizer - {ARM_PSNR_GAP_DB:g})", arm.arm_psnr >= floor
        )
    if arm.motion_ratio is not None:
        low, high = MOTION_RATIO
        targets[f"action WM motion ratio (rollout's frame-to-frame change over the real one), {steps}"] = target_row(
            arm.motion_ratio, f"in [{low}, {high}]", low <= arm.motion_ratio <= high
        )
    return targets


def world_model_targets(
    fidelity: dict,
    done: dict,
    rewards: "RewardReadings | dict",
    action_time: TrainingTime | None = None,
    fidelity_ind: dict | None = None,
    done_ind: dict | None = None,
) -> dict:
    """The world models' targets: controllability and open-loop fidelity in domain (`fidelity_ind`, when the scale
    has new starts of the training scenes) and out of domain (`fidelity`), the done signal (and, `done_ind`, on the
    validation episodes that did not choose its threshold), the goals and the reward on held-out OOD episodes; with
    the action model's training time (read from its held-out curve), its minutes."""
    targets = fidelity_targets(fidelity_ind, "ind") if fidelity_ind is not None else {}
    targets |= fidelity_targets(fidelity, "ood")
    if action_time is not None:
        minutes = action_time.seconds / 60
        targets["bench action WM training minutes on this machine"] = target_row(
            minutes,
            f"<= {ACTION_WM_TRAIN_MINUTES}",
            minutes <= ACTION_WM_TRAIN_MINUTES,
            f"{action_time.step} steps; evaluations excluded",
        )
    targets |= done_targets(DoneReport.from_json(done))
    if done_ind is not None:
        targets |= done_ind_targets(DoneReport.from_json(done_ind))
    rewards = RewardReadings.from_json(rewards)
    targets |= goal_targets(rewards)
    targets["world-model reward: ROC-AUC of the return, held-out OOD episodes"] = reward_target(rewards)
    return targets


def goal_targets(rewards: RewardReadings) -> dict:
    """The text model's goals from held-out starts: reached within the horizon, nearer the real success than the
    start, nearer than another family's goal."""
    goals, successful = rewards.goals, f"{rewards.goals.successful_starts} successful episodes"
    reached, nearer = goals.reached_within_horizon, goals.nearer_final_than_start
    own = goals.final_nearer_own_goal_than_other_instructions
    return {
        "goal: text model reaches done within the family's horizon (share of held-out starts)": target_row(
            reached, f">= {GOAL_REACHED}", reached >= GOAL_REACHED, f"{goals.starts} starts"
        ),
        f"goal frame nearer the real final frame than the start ({rewards.similarity} similarity)": target_row(
            nearer, f">= {GOAL_NEARER_FINAL}", nearer is not None and nearer >= GOAL_NEARER_FINAL, successful
        ),
        "goal made under its own instruction nearer the real success than another family's goal": target_row(
            own,
            f">= {GOAL_OWN_INSTRUCTION}",
            own is not None and own >= GOAL_OWN_INSTRUCTION,
            f"{successful}, the same start under another family's instruction",
        ),
    }


def done_targets(done: DoneReport) -> dict:
    """The chosen done source's ROC-AUCs on held-out OOD episodes, teacher forced and open loop, and the episodes it
    calls done at its threshold."""
    targets, source = {}, done.source
    for mode, goal in (("teacher_forced", DONE_ROC_AUC_TEACHER_FORCED), ("open_loop", DONE_ROC_AUC_OPEN_LOOP)):
        reading, words = done.chosen.reading(mode), mode.replace("_", " ")
        if reading is None:
            continue
        auc, c = reading.frame_roc_auc, reading.confusion
        targets[f"done ROC-AUC, {words}, frames of held-out OOD episodes ({source})"] = target_row(
            auc, f">= {goal}", auc is not None and auc >= goal, f"episodes: {number(reading.episode_roc_auc)}"
        )
        if mode == "open_loop" and c.successful:
            called = c.success_called_done / c.successful
            targets[f"done: successful episodes called done at the threshold, open loop ({source})"] = target_row(
                called,
                f">= {DONE_SUCCESS_CALLED_DONE}",
                called >= DONE_SUCCESS_CALLED_DONE,
                f"{c.success_called_done} of {c.successful}",
            )
        rate = c.failed_called_done_rate
        targets[f"done: failed episodes called done at the threshold, {words} ({source})"] = target_row(
            rate,
            f"<= {DONE_FAILED_CALLED_DONE}",
            rate is not None and rate <= DONE_FAILED_CALLED_DONE,
            f"threshold {done.theta:.3f} chosen on validation episodes; {c.failed_called_done} of {c.failed} failed, "
            f"{c.success_called_done} of {c.successful} successful called done",
        )
    return targets


def done_ind_targets(done: DoneReport) -> dict:
    """The chosen source open loop on validation episodes of the training scenes that did not choose its threshold
    (issue 70): the successful episodes it calls done, and the failed ones."""
    reading, source = done.chosen.reading("open_loop"), done.source
    if reading is None or reading.confusion is None:
        return {}
    c, where = reading.confusion, f"open loop, IND episodes of its own set ({source})"
    called = c.success_called_done / c.successful if c.successful else None
    rate = c.failed_called_done_rate
    detail = f"threshold {done.theta:.3f}; frame ROC-AUC {number(reading.frame_roc_auc)}"
    return {
        f"done: successful episodes called done at the threshold, {where}": target_row(
            called,
            f">= {DONE_SUCCESS_CALLED_DONE}",
            called is not None and called >= DONE_SUCCESS_CALLED_DONE,
            f"{c.success_called_done} of {c.successful}; {detail}",
        ),
        f"done: failed episodes called done at the threshold, {where}": target_row(
            rate,
            f"<= {DONE_FAILED_CALLED_DONE_IND}",
            rate is not None and rate <= DONE_FAILED_CALLED_DONE_IND,
            f"{c.failed_called_done} of {c.failed}",
        ),
    }


def reward_target(rewards: "RewardReadings | dict") -> dict:
    """The world-model return's ROC-AUC on held-out episodes (a reward report), above the baselines it holds."""
    rewards = RewardReadings.from_json(rewards)
    ours = rewards.world_model.roc_auc_of_return
    baselines = {k: rewards.returns[k].roc_auc_of_return for k in REWARD_BASELINES if k in rewards.returns}
    beats = all(ours is not None and (v is None or ours > v) for v in baselines.values())
    return target_row(
        ours,
        f">= {REWARD_ROC_AUC}" + "".join(f", above {k} ({number(v)})" for k, v in baselines.items()),
        ours is not None and ours >= REWARD_ROC_AUC and beats,
        f"similarity: {rewards.similarity}; done: {rewards.done_source} at {rewards.theta:.3f}",
    )


def agreement_targets(ladder: dict, open_loop_rewards: dict | None = None, split: str = "ood") -> dict:
    """Whether the world model judges policies as the simulator does: per-episode agreement and the ladder's ranking
    (`evaluation/ladder.py`'s ladder.json), and the world-model return of held-out episodes generated open loop
    from their recorded actions (`roboscape-reward-report --frames=open_loop`)."""
    ladder = Ladder.from_json(ladder)
    c, n, rho = ladder.confusion, len(ladder.policies), ladder.spearman_return_vs_success
    apart = ladder.apart_rungs or []
    balanced = ladder.balanced_accuracy
    targets = {
        f"agreement: balanced accuracy of world-model success against the simulator's, per episode, {split.upper()}": (
            target_row(
                balanced,
                f">= {AGREEMENT_BALANCED_ACCURACY}",
                balanced is not None and balanced >= AGREEMENT_BALANCED_ACCURACY,
                f"{ladder.episodes} paired episodes of {n} policies; simulator successes called success "
                f"{c.sim_success_wm_success}/{c.simulator_successes}, "
                f"failures called success {c.sim_failure_wm_success}/{c.simulator_failures}",
            )
        ),
        f"ladder: Spearman of the world model's mean return against simulator success, {split.upper()}": target_row(
            ladder.apart_spearman,
            f">= {LADDER_SPEARMAN} over >= {LADDER_RUNGS} policies the simulator tells apart",
            (ladder.apart_spearman or -1.0) >= LADDER_SPEARMAN and len(apart) >= LADDER_RUNGS,
            f"{_apart(ladder.told_apart, apart, n)}; over all {n}: {number(rho)}; simulator success "
            + ", ".join(f"{r:.2f}" for r in ladder.simulator_success_rate)
            + "; world-model mean return "
            + ", ".join(f"{r:.1f}" for r in ladder.world_model_mean_return),
        ),
    }
    if open_loop_rewards is not None:
        dense = RewardReadings.from_json(open_loop_rewards).dense.roc_auc_of_return
        targets["reward: ROC-AUC of the world-model return, held-out OOD episodes generated open loop"] = reward_target(
            open_loop_rewards
        )
        targets["reward: ROC-AUC of the dense term alone, held-out OOD episodes generated open loop"] = target_row(
            dense, f">= {REWARD_DENSE_ROC_AUC}", dense is not None and dense >= REWARD_DENSE_ROC_AUC
        )
    return targets


def _apart(told_apart: bool | None, apart: list[int], n: int) -> str:
    if told_apart is None:
        return f"{n} policies, their simulator intervals not recorded"
    if told_apart:
        return f"{n} policies, every rung's simulator interval apart from the next"
    return f"{len(apart)} of {n} policies told apart (rungs {', '.join(map(str, apart))})"
