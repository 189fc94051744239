#!/usr/bin/env bash
# The world models trained on a lent GPU machine (the `device` tool), from a bench run's data packed here.
#
# Here:
#   bash scripts/experiments/device_world_models.sh pack outputs/bench   # .gpu/ (carry it): caches, sets, packages
#   bash scripts/experiments/device_world_models.sh pack - env          # no run's data; PyAV and starts for roboscape_wm
#   bash scripts/experiments/device_world_models.sh unpack FILES CONTROL [DEST]  # a call's files (read-only) ->
#        DEST/CONTROL/pretrained_model (DEST: outputs/gpu_world_models); once action and text are there, the run
#        goes on with them: roboscape-demo --scale=bench --output_dir=outputs/bench --world_models=DEST
#   CLAIM=DIR/pack bash scripts/experiments/device_world_models.sh pack outputs/bench  # also the experiment's runs
#        in the world model (roboscape-experiment --world_model_runs=DIR writes DIR/pack), for mode claim
#   bash scripts/experiments/device_world_models.sh unpack-runs FILES DIR  # claim's runs -> DIR/runs; then the
#        same roboscape-experiment command again takes them and goes on here
# There (each mode prepares the machine first, once; its files land in $OUT):
#   bash scripts/experiments/device_world_models.sh bench STEPS BATCH [BATCH..] # benchmark_wm_training.py's tables
#        (random token caches: `pack -` will do)
#   bash scripts/experiments/device_world_models.sh sweep STEPS BATCH LR [LR..] # short action runs, held-out at the end
#   [SEEDS="0 1"] bash scripts/experiments/device_world_models.sh train CONTROL STEPS BATCH LR LIMIT_S [EVAL_FREQ] [BUDGET_S]
#        # BUDGET_S: seconds of training (its steps fit them); SEEDS: models side by side, back as CONTROL_sSEED
#   bash scripts/experiments/device_world_models.sh generation          # issue 48: GPU tests, race, memory
#        (PARTS="tests memory race views env" by default; RACE_BATCHES, VIEW_BATCHES, ENV_BATCHES)
#   bash scripts/experiments/device_world_models.sh claim A_S T_S PPO_S [BATCH] [LR]
#        # issue 49 in one call: the action model for A_S seconds of training (then its done tuning), then the text
#        # model for T_S beside the ensemble's members (their share of A_S), then the packed runs in them (each PPO_S
#        # s of PPO's clock, side by side); back: runs.tgz.part-* (the runs, the done report, the models' curves),
#        # logs. The call lasts about A_S + max(T_S, members) + PPO_S + 250 s (start-up, compilation, done tuning,
#        # goals, saves): `claim 150 75 75` should fit a 600 s call, unmeasured until a lease runs it.
#        # PHASE=models stops once the models and members are trained (they stay in /tmp/wmgpu), and PHASE=runs, the
#        # next call on the still-warm machine (it goes back after 30 s idle), runs PPO in them: two calls give the
#        # models and PPO more of a 900 s lease than one call (`PHASE=models ... claim 230 115 0`, then
#        # `PHASE=runs ... claim 0 0 180`: scripts/experiments/README.md).
# A dry run of a mode here, on the CPU, imports only what the device will have (-S: no .venv editable installs):
#   OUT=/tmp/out PY="$PWD/.venv/bin/python -S" PYTHONPATH=$PWD/.venv/lib/python3.12/site-packages \
#     bash scripts/experiments/device_world_models.sh train action 4 4 1e-3 300 2
#
# The GPU image has PyTorch but not LeRobot's data stack: `pack` takes the pure-Python packages training imports from
# .venv (2.5 MB compressed) and a stand-in for PyAV, never called (training reads token caches, not videos). The
# token caches travel exported (tokenizer/token_cache.py) and train without their datasets. What comes back is at most
# 8 files of 16 MiB: a model's weights in bf16, cut in pieces, and a tarball of its logs and curves; or (claim) the
# PPO runs made in the models, which stay there.
# WM=bench runs a dry run's models at the bench preset (the gpu preset trains at ~1 step/min on 2 CPU cores).
# SLACK=S adds S seconds to each model's time limit beyond its training budget: on the CPU a dry run's held-out
# evaluation and done tuning after training take minutes (measured 2026-11-28: 150 s were too few for the action
# model; SLACK=400 is the dry run's).
set -uo pipefail
mode=$1; shift
G=$(pwd)/.gpu
W=/tmp/wmgpu
SITE=(lerobot datasets dill draccus einx farama_notifications frozendict gymnasium loguru lpips mergedeep multiprocess
      _multiprocess torch_einops_utils vector_quantize_pytorch)

if [ "$mode" = pack ]; then
  RUN=$1; SP=.venv/lib/python3.12/site-packages
  rm -rf .gpu && mkdir -p .gpu/stub/av .gpu/stub/av-15.1.0.dist-info
  start=$(date +%s)
  # PACK_ARGS: pack_world_models.py's own flags (e.g. "--ind-starts 16 --ood-starts 16", the claim's at 64 scenes)
  if [ "$RUN" != - ]; then
    .venv/bin/python scripts/experiments/pack_world_models.py --run "$RUN" --out .gpu/data ${PACK_ARGS:-} || exit 1
  fi
  if [ -n "${CLAIM:-}" ]; then
    [ -f "$CLAIM/plan.json" ] || { echo "CLAIM=$CLAIM has no plan.json (roboscape-experiment --world_model_runs=DIR writes DIR/pack)" >&2; exit 1; }
    # xz, since the pack must fit the 64 MiB that travel beside the repository: the starts and done sets are token
    # arrays it shrinks 4-30x (at 64 scenes 11.7 MB -> 0.9 MB), and the tokenizer, when the data's, goes once.
    same=(); diff -rq "$CLAIM/tokenizer" .gpu/data/tokenizer > /dev/null 2>&1 && same=(--exclude=./tokenizer)
    tar cJf .gpu/claim.tar.xz "${same[@]}" -C "$CLAIM" . || exit 1
  fi
  # The generation race's references (mode generation only): 1xgpt's model code (the `fetch` tool's mirror) and our
  # package before the cache was filled block by block (benchmark_cache_memory.py's reference). Training needs
  # neither: without the mirror, the pack goes on without them.
  X1=/work/.mirror/1x-technologies+1xgpt/repo
  if [ -d $X1 ]; then
    git --git-dir=$X1 archive HEAD genie | gzip > .gpu/1xgpt.tgz || exit 1
    git archive da043e0 lerobot_roboscape | gzip > .gpu/before.tgz || exit 1
  else
    echo "no $X1 (fetch github:1x-technologies/1xgpt): packed without the generation race's references"
  fi
  if [ "${2:-}" = env ]; then  # roboscape_wm timed there: PyAV (40 MB: the image lacks it) and 128 px starts
    tar czf .gpu/av.tgz -C $SP av av.libs $(cd $SP && ls -d av-*.dist-info) || exit 1
    .venv/bin/roboscape-collect --repo_id=local/roboscape_demos --root=.gpu/envdemo/datasets/roboscape_demos \
      --families='[push]' --max_scenes=1 --episodes_per_scene=2 --image_size=128 --workers=0 > /dev/null || exit 1
  fi
  names=(); for p in "${SITE[@]}"; do names+=("$p" $(cd $SP && ls -d ${p#_}-*.dist-info 2>/dev/null)); done
  tar czf .gpu/site.tgz --exclude=__pycache__ -C $SP "${names[@]}"
  cat > .gpu/stub/av/__init__.py <<'PY'
"""Stand-in for PyAV on the device machine: attribute access succeeds (LeRobot's imports and annotations), calls fail."""


class _Absent:
    def __init__(self, name):
        self._name = name

    def __getattr__(self, attr):
        return _Absent(f"{self._name}.{attr}")

    def __call__(self, *args, **kwargs):
        raise ImportError(f"{self._name}: PyAV is not installed on the device machine (a stand-in module is)")

    def __or__(self, other):
        return self

    __ror__ = __or__


class _Logging(_Absent):
    WARNING, ERROR, INFO, DEBUG = 30, 40, 20, 10


logging = _Logging("av.logging")


def __getattr__(name):
    return _Absent(f"av.{name}")
PY
  printf 'Metadata-Version: 2.1\nName: av\nVersion: 15.1.0\n' > .gpu/stub/av-15.1.0.dist-info/METADATA
  packed=$(du -b --apparent-size -s .gpu | cut -f1)
  echo "packed in $(( $(date +%s) - start )) s, $packed bytes in all:"
  find .gpu -maxdepth 2 -type f -printf '%10s %p\n' | sort -n
  # A lease carries the repository's files and the pack together, 64 MiB at most: refuse here, not there.
  tree=$(git ls-files -co --exclude-standard -z | xargs -0 du -cb --apparent-size 2>/dev/null | tail -1 | cut -f1)
  carried=$(( 64 * 1024 * 1024 ))
  if [ $(( packed + tree )) -gt $carried ]; then
    echo "the pack ($packed bytes) and the repository's files ($tree) exceed the 64 MiB a lease carries: pack" \
      "less (PACK_ARGS, e.g. fewer controllability starts)" >&2
    exit 1
  fi
  echo "with the repository's files: $(( packed + tree )) of $carried bytes a lease carries"
  exit 0
fi

if [ "$mode" = unpack ]; then  # here: a call's weight pieces -> a model folder that from_pretrained loads
  FILES=$1; CONTROL=$2; DEST=${3:-outputs/gpu_world_models}
  rm -rf "$DEST/$CONTROL" && mkdir -p "$DEST/$CONTROL" || exit 1
  tar xzf "$FILES/${CONTROL}_run.tgz" -C "$DEST/$CONTROL" || exit 1
  cat "$FILES/${CONTROL}.bf16.part-"* > "$DEST/$CONTROL/model.bf16.safetensors"
  .venv/bin/python - "$DEST/$CONTROL" <<'PY'
import sys
from pathlib import Path
from safetensors.torch import load_file, save_file
root = Path(sys.argv[1])
tensors = {k: v.float() if v.is_floating_point() else v for k, v in load_file(root / "model.bf16.safetensors").items()}
save_file(tensors, root / "pretrained_model" / "model.safetensors")
(root / "model.bf16.safetensors").unlink()
print(f"{root / 'pretrained_model'}: {len(tensors)} tensors")
PY
  exit $?
fi

if [ "$mode" = unpack-runs ]; then  # here: claim's runs -> DIR/runs, where roboscape-experiment takes them
  FILES=$1; DIR=$2
  rm -rf "$DIR/runs" && mkdir -p "$DIR" || exit 1
  cat "$FILES/runs.tgz.part-"* | tar xz -C "$DIR" || exit 1
  echo "$DIR/runs: $(ls "$DIR/runs/rl" | tr '\n' ' ')"
  exit 0
fi

# ---- on the device machine ----------------------------------------------------------------------------------------
T0=$(date +%s)  # the call's start: claim keeps its PPO inside DEADLINE seconds of it
# The repository's packages as the .venv's editable installs name them (roboscape_core, the policy and env plugins).
R=$(pwd)
export PYTHONPATH=$G/stub:$W/site:$R:$R/packages/roboscape_core:$R/policies/lerobot_policy_roboscape_mlp:$R/plugins/lerobot_env_roboscape:$R/policies/lerobot_policy_openvla${PYTHONPATH:+:$PYTHONPATH}
export PYTHONUNBUFFERED=1
PY=${PY:-python3}  # a dry run here: PY="$PWD/.venv/bin/python -S" with the .venv's site-packages last on PYTHONPATH
if [ ! -f $W/unpacked ]; then
  mkdir -p $W/site $W/sets $W/caches $W/1xgpt $W/before
  tar xzf $G/site.tgz -C $W/site || exit 3
  if [ -f $G/claim.tar.xz ]; then  # the claim's pack (Python's tarfile: the image may lack xz)
    $PY -c "import tarfile; tarfile.open('$G/claim.tar.xz').extractall('$W/claim', filter='data')" || exit 3
    [ -d $W/claim/tokenizer ] || cp -r $G/data/tokenizer $W/claim/tokenizer || exit 3
  fi
  if [ -f $G/1xgpt.tgz ]; then tar xzf $G/1xgpt.tgz -C $W/1xgpt && tar xzf $G/before.tgz -C $W/before || exit 3; fi
  touch $W/unpacked
fi
keep() { tr '\r' '\n' | awk '!/it\/s|s\/it/ || /\| *[0-9]*00\//'; }  # the progress bar every 100 steps
if [ "$mode" = bench ]; then  # random token caches: no run's data (pack -)
  STEPS=$1; shift; mid=${@:$(( ($# + 1) / 2 )):1}  # the bench preset over the batches, the GPU preset at the middle one
  $PY scripts/benchmarks/benchmark_wm_training.py --presets bench --batch-sizes "$@" --steps $STEPS \
    --episodes 2560 --json $OUT/benchmark.json 2>&1 | keep | tee $OUT/benchmark.md
  $PY scripts/benchmarks/benchmark_wm_training.py --presets gpu --batch-sizes $mid --steps $STEPS --episodes 2560 \
    --json $OUT/benchmark_gpu.json 2>&1 | keep | tee -a $OUT/benchmark.md
  exit 0
fi
if [ "$mode" = generation ]; then  # PARTS: a subset of "tests memory race views env", in that order (default all)
  PARTS=" ${PARTS:-tests memory race views env} "
  [ -d $W/1xgpt/genie ] || { echo "packed without 1xgpt's code: fetch github:1x-technologies/1xgpt, pack again" >&2; exit 2; }
  if [[ $PARTS == *" tests "* ]]; then
    $PY -m pytest -p no:cacheprovider --noconftest -n 0 -q -m gpu tests/world_model/test_world_model.py 2>&1 \
      | tail -25 | tee $OUT/gpu_tests.txt
  fi
  if [[ $PARTS == *" memory "* ]]; then
    for code in $W/before ""; do  # what a generation holds after its prompt: before, then now
      PYTHONPATH=$code${code:+:}$PYTHONPATH $PY scripts/benchmarks/benchmark_cache_memory.py --batch 64 2>&1 | tail -4
    done | tee $OUT/cache_memory.txt
  fi
  if [[ $PARTS == *" race "* ]]; then
    $PY scripts/benchmarks/benchmark_world_model.py --gpu-only --paper-code $W/1xgpt --batch-sizes ${RACE_BATCHES:-1 16 64 max} \
      --memory-snapshot $W/snapshot.pickle 2>&1 | tee $OUT/race.txt
    gzip -c $W/snapshot.pickle > $OUT/snapshot.pickle.gz
  fi
  if [[ $PARTS == *" views "* ]]; then  # the env's frame (two views): ours alone, batch 1 to the largest that fits
    $PY scripts/benchmarks/benchmark_world_model.py --gpu-only --views 2 --batch-sizes ${VIEW_BATCHES:-1 16 64 128 max} \
      2>&1 | tee $OUT/two_views.txt
  fi
  if [[ $PARTS == *" env "* ]] && [ -f $G/av.tgz ]; then  # roboscape_wm (generation, decoding, reward), 128 px starts
    mkdir -p $W/av && tar xzf $G/av.tgz -C $W/av
    PYTHONPATH=$W/av:$PYTHONPATH $PY scripts/benchmarks/benchmark_envs.py --random-preset paper --no-simulator \
      --demo-dir $G/envdemo --batch-sizes ${ENV_BATCHES:-1 16 64 128 256 512} --precisions bfloat16 --steps 40 2>&1 \
      | grep -v "^Loading weights" | tee $OUT/env.txt
  fi
  ls -la $OUT; exit 0
fi
if [ ! -f $W/ready ]; then
  for s in ind ood; do  # Python's lzma: the image may lack xz
    $PY -c "import lzma, shutil; shutil.copyfileobj(lzma.open('$G/data/$s.safetensors.xz'), open('$W/sets/$s.safetensors', 'wb'))" || exit 3
  done
  $PY - <<PY || exit 3
from lerobot_roboscape.tokenizer.token_cache import import_token_cache
import torch
for name in ("demos", "explore"):
    path = import_token_cache("$G/data/" + name + ".xz", "$W/caches")
    (path.parent / (name + ".path")).write_text(str(path))
print("caches imported;", torch.cuda.get_device_name() if torch.cuda.is_available() else "no GPU", "torch", torch.__version__)
PY
  touch $W/ready
fi
D=$G/data
common=(--tokenizer=$D/tokenizer --wm.type=${WM:-gpu} --dataset.repo_id=local/roboscape_demos
        --token_cache=$(cat $W/caches/demos.path) --train.mixed_precision=bf16 --train.log_freq=50)
member=(--wm.control=action --exploration.repo_id=local/roboscape_explore --exploration_share=0.25
        --exploration_token_cache=$(cat $W/caches/explore.path))
# The action model is read on held-out starts as it trains; the ensemble's members (the same data) are not: their
# curve serves nothing, and on the CPU its generation outlasted their time limit (dry run, 2026-11-28).
action=("${member[@]}" --heldout_starts=[$W/sets/ind.safetensors,$W/sets/ood.safetensors] --done_tuning_episodes=${DONE_EPISODES:-32})
# fit CONTROL STEPS BATCH LR LIMIT [EVAL] [BUDGET_S]: train one model into $W/NAME (log: $OUT/NAME.log; NAME is
# CONTROL, or CONTROL_sSEED with SEED set), for BUDGET_S seconds if given (--train.time_budget_s: its steps fit the
# time, whatever the GPU's pace); prints the model, the final one or the last checkpoint of a run the limit stopped.
fit() {
  local control=$1 steps=$2 bs=$3 lr=$4 limit=$5 eval=${6:-500} name=$1${SEED:+_s$SEED} started=$(date +%s) extra=()
  local run=$W/$name
  rm -rf $run
  [ "$control" = action ] && extra=("${action[@]}" --train.eval_freq=$eval) || extra=(--wm.control=text)
  [ -n "${7:-}" ] && extra+=(--train.time_budget_s=$7)
  [ -n "${SEED:-}" ] && extra+=(--train.seed=$SEED)
  timeout $limit $PY -m lerobot_roboscape.cli.train_wm "${common[@]}" "${extra[@]}" --train.steps=$steps \
    --train.batch_size=$bs --train.lr=$lr --train.save_freq=$eval --output_dir=$run 2>&1 | keep > $OUT/$name.log
  echo "$name rc ${PIPESTATUS[0]} seconds $(( $(date +%s) - started ))" | tee -a $OUT/$name.log >&2
  local model=$run/pretrained_model
  [ -f $model/model.safetensors ] || model=$(ls -d $run/checkpoints/*/pretrained_model 2>/dev/null | tail -1)
  [ -n "$model" ] || { echo "$name: no model saved in $limit s" >&2; return 1; }
  echo $model
}
# records CONTROL DEST: a trained model's logs and curves (not its weights)
records() { mkdir -p $2; for f in train_log.jsonl heldout_curve.jsonl train_config.json done_tuning.json; do cp $W/$1/$f $2/ 2>/dev/null; done; true; }

case $mode in
  sweep)
    STEPS=$1; BS=$2; shift 2
    for LR in "$@"; do
      run=$W/sweep_lr$LR; rm -rf $run
      $PY -m lerobot_roboscape.cli.train_wm "${common[@]}" "${action[@]}" --train.steps=$STEPS --train.batch_size=$BS \
        --train.lr=$LR --train.eval_freq=$STEPS --train.save_freq=$STEPS --done_tuning_steps=0 --output_dir=$run 2>&1 \
        | keep > $OUT/sweep_lr$LR.log
      $PY -c "import json,sys; c=[json.loads(l) for l in open('$run/heldout_curve.jsonl')][-1]; \
t=[json.loads(l) for l in open('$run/train_log.jsonl')][-1]; print(json.dumps({**c, **t, 'lr': $LR, 'batch': $BS}))" \
        | tee -a $OUT/sweep.jsonl
    done ;;
  train)
    CONTROL=$1; STEPS=$2; BS=$3; LR=$4; LIMIT=$5; EVAL=${6:-500}; BUDGET=${7:-}
    # SEEDS="0 1": one model per seed, side by side (a bench-preset model leaves the GPU most of its room), each
    # back as CONTROL_sSEED; without SEEDS one model, back as CONTROL.
    pids=()
    for seed in ${SEEDS:--}; do
      [ "$seed" = - ] && seed=
      name=$CONTROL${seed:+_s$seed}
      (
        model=$(SEED=$seed fit $CONTROL $STEPS $BS $LR $LIMIT $EVAL $BUDGET) || exit 1
        $PY - $model $W/$name.bf16.safetensors <<'PY'
import sys
from safetensors.torch import load_file, save_file
tensors = {k: v.bfloat16() if v.is_floating_point() else v for k, v in load_file(sys.argv[1] + "/model.safetensors").items()}
save_file(tensors, sys.argv[2])
PY
        split -b 15M $W/$name.bf16.safetensors $OUT/$name.bf16.part-
        mkdir -p $W/pack_$name/pretrained_model && cp $model/config.json $W/pack_$name/pretrained_model/
        cp -r $model/text_encoder $W/pack_$name/pretrained_model/ 2>/dev/null
        records $name $W/pack_$name
        tar czf $OUT/${name}_run.tgz -C $W/pack_$name . && rm -rf $W/pack_$name
      ) &
      pids+=($!)
    done
    failed=0; for pid in "${pids[@]}"; do wait $pid || failed=1; done  # a seed that saved nothing fails the call
    ls -la $OUT; exit $failed ;;
  claim)
    A_S=$1; T_S=$2; PPO_S=$3; BS=${4:-64}; LR=${5:-1e-3}
    C=$W/claim
    [ -f $C/plan.json ] || { echo "no $C/plan.json: pack with CLAIM=<roboscape-experiment's --world_model_runs>/pack" >&2; exit 2; }
    start=$(date +%s)
    if [ "${PHASE:-all}" = runs ]; then  # the models a PHASE=models call left on this machine (still warm)
      [ -f $W/claim_models ] || { echo "PHASE=runs: no $W/claim_models; call PHASE=models first, on a warm machine" >&2; exit 2; }
      { read -r action_model; read -r text_model; read -r list; } < $W/claim_models
    else
      action_model=$(fit action 1000000 $BS $LR $(( A_S + 150 + ${SLACK:-0} )) 500 $A_S) || exit 1
      # Then the text model and the ensemble's members (the action model with its top redrawn, trained alone) side by
      # side: their budgets are wall-clock, and one 30M model leaves the GPU room.
      fit text 1000000 $BS $LR $(( T_S + 90 + ${SLACK:-0} )) 500 $T_S > $W/text.path &
      read -r N R SHARE <<< "$($PY -c "import json; p=json.load(open('$C/plan.json')); e=p.get('ensemble') or {}; \
print(e.get('members', 0) if any(r['ensemble'] for r in p['runs'].values()) else 0, e.get('retrain_blocks'), e.get('steps_share', 1))")"
      members=()
      if [ "$N" -gt 0 ]; then
        budget=$($PY -c "print(max(round($A_S * $SHARE), 1))")
        top=(); [ "$R" != None ] && top=(--init_from=$action_model --retrain_blocks=$R)
        for seed in $(seq 1 $N); do
          timeout $(( budget + 120 + ${SLACK:-0} )) $PY -m lerobot_roboscape.cli.train_wm "${common[@]}" "${member[@]}" "${top[@]}" \
            --train.seed=$seed --train.steps=1000000 --train.time_budget_s=$budget --train.batch_size=$BS \
            --train.lr=$LR --train.save_freq=1000000 --done_tuning_steps=0 --output_dir=$W/member$seed 2>&1 \
            | keep > $W/member$seed.log &
          members+=("$W/member$seed/pretrained_model")
        done
      fi
      wait
      text_model=$(cat $W/text.path); [ -n "$text_model" ] || exit 1
      for seed in $(seq 1 $N); do tail -3 $W/member$seed.log; done | tee -a $OUT/claim.log
      echo "models and members in $(( $(date +%s) - start )) s" | tee -a $OUT/claim.log
      # The models' logs and curves, back even if PPO is cut (at most 8 files come back: 4 here, the runs in <= 4).
      for control in action text; do records $control $W/early/$control; done; tar czf $OUT/world_models.tgz -C $W/early .
      # A member that did not save in its budget is left out: the ensemble's runs then use the others, or fail alone.
      saved=(); for m in "${members[@]}"; do
        if [ -f $m/model.safetensors ]; then saved+=("$m"); else echo "member $m not saved" | tee -a $OUT/claim.log; fi
      done
      list=$(IFS=,; echo "${saved[*]}")
      printf '%s\n' "$action_model" "$text_model" "$list" > $W/claim_models
      [ "${PHASE:-all}" = models ] && { ls -la $OUT; exit 0; }
    fi
    # PPO's clock fits what is left of the call (DEADLINE s, default 570 of a 600 s call), ~100 s kept for the done
    # report, the goals, the processes' start, the replay's rollouts and the tarball.
    left=$(( ${DEADLINE:-570} - ($(date +%s) - T0) - 100 ))
    if [ $left -lt $PPO_S ]; then echo "PPO's clock cut from $PPO_S s to $left s to end inside the call" | tee -a $OUT/claim.log; PPO_S=$left; fi
    [ $PPO_S -ge 10 ] || { echo "no time left for PPO" | tee -a $OUT/claim.log; exit 1; }
    rm -rf $W/runs
    $PY -m lerobot_roboscape.cli.run_world_model_pack --pack=$C --action=$action_model --text=$text_model \
      "--members=[$list]" --output_dir=$W/runs --time_budget_s=$PPO_S 2>&1 | keep | tee -a $OUT/claim.log
    [ -f $W/runs/results.json ] || exit 1
    for control in action text; do records $control $W/runs/world_models/$control; done
    tar czf - -C $W runs | split -b 15M - $OUT/runs.tgz.part-
    echo "claim done in $(( $(date +%s) - start )) s" | tee -a $OUT/claim.log
    ls -la $OUT ;;
  *) echo "unknown mode $mode" >&2; exit 2 ;;
esac
