#!/usr/bin/env bash
# tools/gpu-check.sh OUTDIR: issue #31's GPU check as one command on a bare lent GPU machine (H100 or
# H200, 16 cores, Python 3.12 with torch preinstalled, no network). From the repository root, with the
# wheels of ../shared/tools/gpu-wheels.sh carried in .whl/ (pybullet, zenoh, mcap, tyro, gymnasium):
#
#   bash tools/gpu-check.sh "$OUT"
#
# (KEEP_DATA=__init__.py,kuka_iiwa,franka_panda,plane,tray,table,cube,checker for gpu-wheels.sh keeps the
# plane's texture too, which pybullet otherwise warns about at every load; no image uses it.)
#
# Steps, each under its own `timeout`; each runs whatever became of the one before (its status and
# time go to summary.txt), so one run yields as much as it can:
#   install  the carried wheels into /tmp/site; PYTHONPATH=/tmp/site:$PWD
#   env      import pybullet, zenoh, mcap, torch; Python, torch, CUDA versions, the GPU, nvidia-smi
#   tests    every test file marking CUDA tests (its CPU tests too) and the SAC/trainer unit tests
#   bench    `mea bench learner --device cuda` for paper C4 and cpu-small C4, eager and with
#            --cuda-graphs: ms/update p50/p99 (the CPU baseline is in docs/results.md, "On a GPU")
#   run      the paper protocol of issue #31 (Block Pull, `mea`, 2 demos, the paper preset, 1 update
#            per env step, 40K env steps, 20 held-out seeds every 1K, 8 actors, the learner on CUDA,
#            with --cuda-graphs where the graphed update passed its test and timed faster) in /tmp,
#            stopped by --duration-seconds at what is left of the check's time less the system
#            bench's share; its evaluation curve, env steps/s, summary, GPU and host memory
#   system   `mea bench system --actors 8` with short windows (GPU_CHECK_SYSTEM_SECONDS, default 110,
#            0 skips it): raw pybullet stepping against the whole stack at 8 actors
# `mea` is run as `python3 -m services.cli` (the project is not installed there).
#
# OUTDIR receives 8 files at most, no folders (the device tool returns 8): summary.txt (each step's
# status and time, the update timings, the curve, the system bench's tables), steps.log (install,
# env, tests, benchmark logs), bench.jsonl (the learner benchmark results), run.log,
# run-resources.csv (GPU utilisation and memory, host memory used, every 5 s), run-eval.jsonl,
# run-summary.json, run-curves.png. The run directory itself stays in /tmp/gpu-check-run
# (checkpoints and weights are too many and too large to return).
#
# Time: GPU_CHECK_SECONDS (default 450) for the whole check; the run gets what the steps before it
# left, less 40 s for its stop and the system bench's share: about 8 minutes in all. Give the device
# command a timeout_s of 600.
#
# pytest: the GPU image has it (and iniconfig, pluggy, packaging, pytest-timeout). Where it does not,
# add its wheels to .whl before carrying it (the install step installs every wheel there):
#   python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#     -d .whl pytest==9.0.3 iniconfig pluggy packaging
#
# Dry mode, GPU_CHECK_DRY=1: every step on this machine's CPU with tiny budgets (the smoke learner,
# 300 env steps, 1 actor), with its Python (.venv's if there is one) and no wheels installed: the
# plumbing shown where there is no GPU (the CUDA tests skip, saying so).
set -u

OUT=${1:?usage: tools/gpu-check.sh OUTDIR}
mkdir -p "$OUT" || exit 2
OUT=$(cd "$OUT" && pwd)
cd "$(dirname "$0")/.." || exit 2
. tools/resources.sh
DRY=${GPU_CHECK_DRY:-0}
TOTAL=${GPU_CHECK_SECONDS:-450}
SUMMARY=$OUT/summary.txt LOG=$OUT/steps.log
RUN_DIR=${GPU_CHECK_RUN_DIR:-/tmp/gpu-check-run}
export PYTHONUNBUFFERED=1 PYTHONDONTWRITEBYTECODE=1
if [ "$DRY" = 1 ]; then
  PY=${PYTHON:-$( [ -x .venv/bin/python ] && echo .venv/bin/python || echo python3 )}
  DEVICE=cpu
else
  PY=${PYTHON:-python3}
  DEVICE=cuda
fi
: >"$SUMMARY"
: >"$LOG"
note() { echo "$*" | tee -a "$SUMMARY"; }
left() { echo $((TOTAL - SECONDS)); }

# step NAME LIMIT LOGFILE COMMAND...: COMMAND under `timeout LIMIT` (SIGINT first when STOP_SIGNAL=INT,
# SIGKILL 20 s later), output appended to LOGFILE (stdout to STDOUT_TO instead, if set), status and
# seconds to summary.txt; never exits.
step() {
  local name=$1 limit=$2 log=$3 t0=$SECONDS rc verdict
  shift 3
  echo "=== $name (limit ${limit} s): $*" >>"$log"
  timeout -s "${STOP_SIGNAL:-TERM}" -k 20 "$limit" "$@" >>"${STDOUT_TO:-$log}" 2>>"$log"
  rc=$?
  case $rc in
    0) verdict=ok ;;
    124 | 137) verdict="TIMED OUT (rc $rc)" ;;
    *) verdict="FAILED (rc $rc)" ;;
  esac
  echo "=== $name: $verdict" >>"$log"
  printf '%-12s %-20s %5d s\n' "$name" "$verdict" $((SECONDS - t0)) | tee -a "$SUMMARY"
  return "$rc"
}

note "gpu-check $(date -u +%FT%TZ) on ${HOSTNAME:-?}: dry=$DRY device=$DEVICE python=$PY budget=${TOTAL}s"
note "git: $(git rev-parse --short HEAD 2>/dev/null || echo '?') with $(git status --porcelain 2>/dev/null | wc -l) changed files"

# --- install ---------------------------------------------------------------------------------------
if [ "$DRY" = 1 ]; then
  note "install      skipped (dry: this machine's packages)"
  export PYTHONPATH=$PWD
elif compgen -G ".whl/*.whl" >/dev/null; then
  step install 120 "$LOG" "$PY" -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/*.whl
  export PYTHONPATH=/tmp/site:$PWD
else
  note "install      NO .whl/ (make it with ../shared/tools/gpu-wheels.sh .whl and carry it)"
  export PYTHONPATH=$PWD
fi

# --- env -------------------------------------------------------------------------------------------
step env 60 "$LOG" "$PY" - <<'PY'
import os, platform, sys
print("python", sys.version.split()[0], platform.machine(), "cores", os.cpu_count())
import torch
print("torch", torch.__version__, "cuda", torch.version.cuda, "cudnn", torch.backends.cudnn.version(),
      "available", torch.cuda.is_available())
if torch.cuda.is_available():
    p = torch.cuda.get_device_properties(0)
    print("gpu", torch.cuda.get_device_name(0), f"{p.total_memory / 2**30:.0f} GiB", f"sm_{p.major}{p.minor}",
          p.multi_processor_count, "SMs")
import importlib.metadata as md
import mcap, numpy, pybullet, zenoh  # noqa: E401,F401 - the carried wheels
def dist(*names):  # the first installed distribution of these names, with its version
    for n in names:
        try:
            return f"{n} {md.version(n)}"
        except md.PackageNotFoundError:
            pass
    return f"{names[0]} ?"
print("numpy", numpy.__version__, "|", dist("pybullet", "pybullet-arm64"), "|", dist("eclipse-zenoh"), "|",
      dist("mcap"), "|", dist("tyro"), "|", dist("gymnasium"))
import pybullet_data
print("pybullet_data", pybullet_data.getDataPath(), sorted(os.listdir(pybullet_data.getDataPath()))[:12])
import services.cli  # the project imports on this Python
print("services.cli imports")
PY
grep -E "^(python|torch|gpu|numpy) " "$LOG" | tee -a "$SUMMARY"
if command -v nvidia-smi >/dev/null; then
  nvidia-smi --query-gpu=name,driver_version,memory.total,memory.used,clocks.max.sm --format=csv >>"$LOG" 2>&1
fi

# --- tests -----------------------------------------------------------------------------------------
if "$PY" -m pytest --version >>"$LOG" 2>&1; then
  mapfile -t cuda_files < <(grep -rl --include='test_*.py' 'mark.cuda' tests | sort)
  tests=("${cuda_files[@]}")
  [ "$DRY" = 1 ] || tests+=(tests/unit/test_sac_losses.py tests/unit/test_trainer.py)  # 3.12, torch 2.11
  step tests "$(( $(left) < 150 ? 60 : 150 ))" "$LOG" "$PY" -m pytest -q -rsfE -p no:cacheprovider "${tests[@]}"
  grep -E "^(SKIPPED|FAILED|ERROR)|[0-9]+ (passed|failed)" "$LOG" | tail -15 | tee -a "$SUMMARY"
  # where an update still waits for the GPU (the networks' own code: a lead for the next speed-up)
  step sync-sites 60 "$LOG" "$PY" -m pytest -q -s -p no:cacheprovider -k never_synchronise \
    tests/unit/test_learner_device.py
  grep -E "host synchronisations" "$LOG" | tail -1 | tee -a "$SUMMARY"
else
  note "tests        NO pytest for $PY (see this script's header for its wheels)"
fi

# --- bench -----------------------------------------------------------------------------------------
if [ "$DRY" = 1 ]; then
  variants=(smoke:c4) cpu_variants=(smoke:c4) updates=(--updates 2 --episodes 8) cpu_updates=(--updates 1 --episodes 8)
else
  variants=(paper:c4 cpu-small:c4) updates=(--updates 50)
fi
: >"$OUT/bench.jsonl"
bench=("$PY" -m services.cli bench learner --consumers 0 --gasv2-presets --checkpoint-episodes 0 --json)
STDOUT_TO=$OUT/bench.jsonl step "bench-$([ "$DRY" = 1 ] && echo dev || echo "$DEVICE")" 150 "$LOG" "${bench[@]}" --device "$DEVICE" \
  --variants "${variants[@]}" "${updates[@]}"
if [ "$DRY" != 1 ]; then  # the same paper update replayed as a CUDA graph (--cuda-graphs)
  STDOUT_TO=$OUT/bench.jsonl step bench-graphs 90 "$LOG" "${bench[@]}" --device "$DEVICE" --cuda-graphs \
    --variants paper:c4 cpu-small:c4 "${updates[@]}"
fi
if [ "$DRY" = 1 ]; then  # the plumbing of a CPU baseline; on the GPU machine its CPU figures are known
  STDOUT_TO=$OUT/bench.jsonl step bench-cpu 90 "$LOG" "${bench[@]}" --device cpu --variants "${cpu_variants[@]}" \
    "${cpu_updates[@]}"
fi
"$PY" - "$OUT/bench.jsonl" <<'PY' | tee -a "$SUMMARY"
import json, sys
for line in open(sys.argv[1]):
    if not line.strip():
        continue
    r = json.loads(line)
    meta = r["meta"]
    print(f"bench learner on {meta.get('device')} {meta.get('gpu') or ''} (torch {meta['torch']}, {meta['threads']} threads)")
    for row in r["results"]["gradient updates"]:
        graphs = " graphed" if row.get("CUDA graphs") else ""
        print(f"  {row['variant'] + graphs:<16} batch {row['batch (episodes)']:>2}  p50 {row['ms/update p50']:9.1f} ms"
              f"  p99 {row['ms/update p99']:9.1f} ms  sample+copy {1e3 * row['sample + tensors s']:7.1f} ms"
              f"  ({row['timed updates']} updates)")
PY

# --- run -------------------------------------------------------------------------------------------
if [ "$DRY" = 1 ]; then
  run_args=(--learner-preset smoke --env-steps 300 --demos 2 --random-steps 50 --eval-every 150 --eval-episodes 1
            --final-eval-episodes 1 --actors 1)
else
  run_args=(--learner-preset paper --env-steps 40000 --demos 2 --eval-every 1000 --eval-episodes 20
            --final-eval-episodes 20 --actors 8)
fi
# the graphed update in the run only where its test passed and it timed faster than the eager one
graphs=$("$PY" - "$OUT/bench.jsonl" "$LOG" <<'PY'
import json, re, sys
eager = graphed = None
for line in open(sys.argv[1]):
    try:
        rows = json.loads(line)["results"]["gradient updates"]
    except (ValueError, KeyError, TypeError):
        rows = []
    for row in rows:
        if row["variant"].startswith("paper"):
            if row.get("CUDA graphs"):
                graphed = row["ms/update p50"]
            else:
                eager = eager or row["ms/update p50"]
log = open(sys.argv[2]).read()
ok = not re.search(r"^(FAILED|ERROR) .*graph", log, re.M)  # the tests step lists them (-rsfE)
print("yes" if ok and graphed is not None and eager is not None and graphed < eager else "no")
PY
)
if [ "$graphs" = yes ]; then
  run_args+=(--learner-args=--cuda-graphs)
fi
note "run          learner with CUDA graphs: $graphs"
SYSTEM=${GPU_CHECK_SYSTEM_SECONDS:-110}
duration=$(( $(left) - 40 - SYSTEM ))
if [ "$duration" -lt 60 ]; then
  note "run          SKIPPED: ${duration} s left of the check's ${TOTAL} s"
else
  rm -rf "$RUN_DIR"
  sample_resources "$OUT/run-resources.csv"
  STOP_SIGNAL=INT step run $((duration + 30)) "$OUT/run.log" "$PY" -m services.cli run --task block_pull \
    --variant equiobs "${run_args[@]}" --learner-device "$DEVICE" --no-record --metrics-port 0 \
    --run-dir "$RUN_DIR" --duration-seconds "$duration" --final-eval-seconds 60 --stop-grace-seconds 15
  kill "$sampler" 2>/dev/null
  wait "$sampler" 2>/dev/null
  cp "$RUN_DIR/eval/history.jsonl" "$OUT/run-eval.jsonl" 2>/dev/null || note "run          no eval/history.jsonl"
  cp "$RUN_DIR/summary.json" "$OUT/run-summary.json" 2>/dev/null || note "run          no summary.json"
  cp "$RUN_DIR/curves.png" "$OUT/run-curves.png" 2>/dev/null
  "$PY" - "$RUN_DIR" <<'PY' | tee -a "$SUMMARY"
import json, sys
from pathlib import Path
run = Path(sys.argv[1])
try:
    rows = [json.loads(x) for x in (run / "eval" / "history.jsonl").read_text().splitlines() if x.strip()]
except OSError:
    rows = []
print("run curve (env steps, weights version, episodes, success rate):")
for r in rows:
    print(f"  {r.get('env_steps'):>6}  v{r.get('version'):<5} {r.get('episodes'):>3}  {r.get('success_rate'):.2f}"
          + ("  (at budget)" if r.get("at_budget") else ""))
if not rows:
    print("  none")
try:
    summary = json.loads((run / "summary.json").read_text())
except (OSError, ValueError):
    summary = {}
if summary:
    s, n = summary.get("elapsed_seconds") or 0.0, summary.get("env_steps") or 0.0
    print(f"run: {s:.0f} s, {n:.0f} env steps ({n / max(s, 1e-9):.1f}/s over the whole run, demos included)")
    for name, inst in sorted(summary.get("instances", {}).items()):
        c = inst.get("counters") or {}
        if inst.get("service") == "learner":
            print(f"  {name}: {c.get('updates', 0):.0f} updates, waited {c.get('wait_seconds', 0):.0f} s, "
                  f"critic loss {c.get('critic_loss', float('nan')):.4g}, replay {c.get('replay_transitions', 0):.0f}")
PY
  tail -5 "$OUT/run-resources.csv" | tee -a "$SUMMARY"
fi

# --- system ----------------------------------------------------------------------------------------
if [ "$SYSTEM" -gt 0 ] && [ "$(left)" -gt 60 ]; then
  window=$(( (SYSTEM - 50) / 3 > 10 ? (SYSTEM - 50) / 3 : 10 ))  # raw, warm-up and stack windows
  STDOUT_TO=/tmp/gpu-check-system.txt step system "$SYSTEM" "$LOG" "$PY" -m services.cli bench system \
    --actors "$([ "$DRY" = 1 ] && echo 1 || echo 8)" --seconds "$window" --warmup-seconds "$window" \
    --run-dir /tmp/gpu-check-system
  cat /tmp/gpu-check-system.txt >>"$SUMMARY" 2>/dev/null
else
  note "system       SKIPPED: $(left) s left of the check's ${TOTAL} s"
fi
note "gpu-check done in ${SECONDS} s"
