#!/usr/bin/env bash
# The bench world models at the BENCH_ON_GPU size on a lent GPU machine (the `device` tool), from the token caches
# of a reduced-scale run here: docs/results/world_model/report.md, "Trained on a GPU".
#
#   bash scripts/experiments/device_world_models.sh pack outputs/wm37    # here: assemble .gpu/ (carry it), about 37 MB
#   bash scripts/experiments/device_world_models.sh run OUT ACTION_STEPS TEXT_STEPS BATCH ACTION_LIMIT_S TEXT_LIMIT_S  # there
#
# The GPU image has PyTorch but not LeRobot's data stack: `pack` copies the pure-Python packages the training imports
# from .venv, and a stand-in for PyAV (never called: training reads the token cache, not videos). The datasets'
# fingerprints read video and mask names and sizes only, so their sizes travel and sparse files stand in there.
set -uo pipefail
mode=$1; shift
G=$(pwd)/.gpu
if [ "$mode" = pack ]; then
  O=$1; SP=.venv/lib/python3.12/site-packages
  grep -qx '/.gpu/' .git/info/exclude || echo /.gpu/ >> .git/info/exclude
  rm -rf .gpu && mkdir -p .gpu/site .gpu/stub/av .gpu/stub/av-15.1.0.dist-info .gpu/data/tokenizer
  for p in lerobot datasets dill draccus einx farama_notifications frozendict gymnasium loguru mergedeep multiprocess \
           _multiprocess torch_einops_utils vector_quantize_pytorch; do
    cp -r $SP/$p .gpu/site/ && cp -r $SP/${p#_}-*.dist-info .gpu/site/ 2>/dev/null
  done
  find .gpu -name __pycache__ -prune -exec rm -rf {} +
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
  for d in demos explore; do
    mkdir -p .gpu/data/$d && cp -r $O/$d/meta $O/$d/data .gpu/data/$d/
    (cd $O/$d && find videos segmentation -type f -printf '%s %p\n' 2>/dev/null) > .gpu/data/$d.sizes.txt
  done
  cp -r $O/token_cache .gpu/data/ && cp -r $O/tokenizer/pretrained_model .gpu/data/tokenizer/
  du -sh --apparent-size .gpu
  exit 0
fi
OUT=$1; AS=$2; TS=$3; BS=$4; AL=$5; TL=$6; W=/tmp/wmgpu; PY=python3
mkdir -p $W $OUT
export PYTHONPATH=$G/stub:$G/site:$(pwd) PYTHONUNBUFFERED=1
for d in demos explore; do
  while read -r size path; do mkdir -p $G/data/$d/$(dirname $path); truncate -s $size $G/data/$d/$path; done < $G/data/$d.sizes.txt
done
$PY -c "import lerobot_roboscape.cli.train_wm, torch; print('imports ok', torch.cuda.get_device_name())" || exit 3
D=$G/data
common=(--tokenizer=$D/tokenizer/pretrained_model --wm.type=bench --cache_dir=$D/token_cache
        --dataset.repo_id=local/roboscape_demos --dataset.root=$D/demos --train.batch_size=$BS
        --train.mixed_precision=no --train.log_freq=250 --train.save_freq=1000)
keep() { tr '\r' '\n' | awk '!/it\/s/ || /\| *[0-9]*000\//'; }
start=$(date +%s)
timeout $AL $PY -m lerobot_roboscape.cli.train_wm "${common[@]}" --wm.control=action --train.steps=$AS \
  --exploration.repo_id=local/roboscape_explore --exploration.root=$D/explore --exploration_share=0.25 \
  --done_tuning_episodes=32 --output_dir=$W/action 2>&1 | keep > $OUT/action.log
echo "ACTION rc ${PIPESTATUS[0]} seconds $(( $(date +%s) - start ))" | tee -a $OUT/action.log
if [ "$TS" != 0 ]; then
  start=$(date +%s)
  timeout $TL $PY -m lerobot_roboscape.cli.train_wm "${common[@]}" --wm.control=text --train.steps=$TS \
    --output_dir=$W/text 2>&1 | keep > $OUT/text.log
  echo "TEXT rc ${PIPESTATUS[0]} seconds $(( $(date +%s) - start ))" | tee -a $OUT/text.log
fi
cd $W
tar czf $OUT/final.tar.gz --exclude=checkpoints action $(ls -d text 2>/dev/null)
n=0
for c in $(ls action/checkpoints | grep -v last); do
  tar rf $OUT/ck$((n / 2)).tar action/checkpoints/$c/pretrained_model; n=$((n + 1))
done
t=$(ls text/checkpoints 2>/dev/null | grep -v last | tail -1)
[ -n "$t" ] && tar cf $OUT/text_ck.tar text/checkpoints/$t/pretrained_model
ls -la $OUT
