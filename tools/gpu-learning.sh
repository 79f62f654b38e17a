#!/usr/bin/env bash
# tools/gpu-learning.sh OUTDIR: learning curves on a lent GPU machine (16 cores, one GPU, no network):
# several `mea run`s at once, each with its learner on CUDA and ACTORS actors, stopped after SECONDS;
# their evaluation curves come back. From the repository root, with the wheels of
# ../shared/tools/gpu-wheels.sh carried in .whl/ (as for tools/gpu-check.sh):
#
#   SEEDS="0 1 2" ACTORS=4 SECONDS_EACH=480 LEARNER_ARGS="--sac.no-share-encoder" \
#     bash tools/gpu-learning.sh "$OUT" [mea run options...]
#
# The runs differ only in --seed; the remaining arguments go to every `mea run` (default: Block Pull,
# MEA, 2 demos, 20K env steps, the cpu-small recipe). Success against env steps does not depend on
# the machine (the replay gate fixes updates per env step), but several actors collect with a policy
# up to a few versions older than one actor's: say so where these curves sit beside CPU ones.
#
# OUTDIR receives at most 8 files: summary.txt (setup, each run's curve, env steps/s, GPU and host
# memory), run-<seed>-eval.jsonl per run, resources.csv (GPU utilisation and memory, host memory),
# runs.log (the launchers' last lines). GPU_LEARNING_DRY=1 runs it on this machine's CPU, tiny.
set -u

OUT=${1:?usage: tools/gpu-learning.sh OUTDIR [mea run options...]}
shift
mkdir -p "$OUT" || exit 2
OUT=$(cd "$OUT" && pwd)
cd "$(dirname "$0")/.." || exit 2
. tools/resources.sh
DRY=${GPU_LEARNING_DRY:-0}
SEEDS=${SEEDS:-0 1 2}
ACTORS=${ACTORS:-4}
EACH=${SECONDS_EACH:-480}
LEARNER_ARGS=${LEARNER_ARGS:-}
export PYTHONUNBUFFERED=1 PYTHONDONTWRITEBYTECODE=1
SUMMARY=$OUT/summary.txt
note() { echo "$*" | tee -a "$SUMMARY"; }
: >"$SUMMARY"

if [ "$DRY" = 1 ]; then
  PY=${PYTHON:-$( [ -x .venv/bin/python ] && echo .venv/bin/python || echo python3 )}
  DEVICE=cpu
  export PYTHONPATH=$PWD
  defaults=(--learner-preset smoke --env-steps 300 --demos 2 --eval-every 150 --eval-episodes 2 --final-eval-episodes 2)
else
  PY=${PYTHON:-python3}
  DEVICE=cuda
  if compgen -G ".whl/*.whl" >/dev/null; then
    "$PY" -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/*.whl >>"$OUT/runs.log" 2>&1 \
      || note "install FAILED (see runs.log)"
    export PYTHONPATH=/tmp/site:$PWD
  else
    note "NO .whl/ (make it with ../shared/tools/gpu-wheels.sh .whl and carry it)"
    export PYTHONPATH=$PWD
  fi
  defaults=(--env-steps 20000 --demos 2)
fi
args=(--task block_pull "${defaults[@]}" "$@")
note "gpu-learning $(date -u +%FT%TZ): device=$DEVICE seeds=[$SEEDS] actors=$ACTORS seconds=$EACH cores=$(getconf _NPROCESSORS_ONLN)"
note "git $(git rev-parse --short HEAD 2>/dev/null || echo '?'), $(git status --porcelain 2>/dev/null | wc -l) changed files"
note "mea run ${args[*]} --learner-args=\"$LEARNER_ARGS\" --actors $ACTORS --learner-device $DEVICE"

sample_resources "$OUT/resources.csv"

pids=()
free_port() { "$PY" -c "import socket; s = socket.socket(); s.bind(('127.0.0.1', 0)); print(s.getsockname()[1])"; }
for seed in $SEEDS; do
  port=$(free_port)
  run_dir=/tmp/gpu-learning/run-$seed
  rm -rf "$run_dir"
  mkdir -p "$(dirname "$run_dir")"
  timeout -s INT -k 60 $((EACH + 90)) "$PY" -m services.cli run "${args[@]}" --seed "$seed" \
    --learner-args="$LEARNER_ARGS" --actors "$ACTORS" --learner-device "$DEVICE" --no-record --metrics-port 0 \
    --listen "tcp/127.0.0.1:$port" --run-dir "$run_dir" --duration-seconds "$EACH" --final-eval-seconds 30 \
    --stop-grace-seconds 20 >"/tmp/gpu-learning/run-$seed.log" 2>&1 &
  pids+=($!)
done
for p in "${pids[@]}"; do wait "$p"; done
kill "$sampler" 2>/dev/null
wait "$sampler" 2>/dev/null

for seed in $SEEDS; do
  run_dir=/tmp/gpu-learning/run-$seed
  cp "$run_dir/eval/history.jsonl" "$OUT/run-$seed-eval.jsonl" 2>/dev/null || note "seed $seed: no eval/history.jsonl"
  { echo "=== seed $seed"; grep -E "ERROR|Traceback|status alive" "/tmp/gpu-learning/run-$seed.log" | tail -8; } >>"$OUT/runs.log"
  "$PY" - "$run_dir" "$seed" <<'PY' | tee -a "$SUMMARY"
import json, sys
from pathlib import Path
run, seed = Path(sys.argv[1]), sys.argv[2]
try:
    rows = [json.loads(x) for x in (run / "eval" / "history.jsonl").read_text().splitlines() if x.strip()]
except OSError:
    rows = []
curve = " ".join(f"{r.get('env_steps')}:{r.get('success_rate'):.2f}" for r in rows)
try:
    s = json.loads((run / "summary.json").read_text())
except (OSError, ValueError):
    s = {}
secs = s.get("elapsed_seconds") or 0.0
steps = sum((i.get("counters") or {}).get("env_steps", 0.0) for i in s.get("instances", {}).values()
            if i.get("service") == "actor")
print(f"seed {seed}: {steps:.0f} env steps in {secs:.0f} s ({steps / max(secs, 1e-9):.1f}/s); curve {curve or 'none'}")
PY
done
note "peak GPU memory MiB $(cut -d, -f3 "$OUT/resources.csv" | sort -n | tail -1), host MiB $(cut -d, -f4 "$OUT/resources.csv" | sort -n | tail -1)"
note "gpu-learning done in ${SECONDS} s"
