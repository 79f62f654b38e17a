# Sourced by tools/gpu-check.sh and tools/gpu-learning.sh: `sample_resources FILE` writes a CSV header
# to FILE, then every 5 s the GPU's utilisation and memory and the host's memory used, in the
# background; the sampler's pid is in $sampler (stop it with `kill "$sampler"; wait "$sampler"`).
sample_resources() {
  echo "time,gpu_util_percent,gpu_memory_used_mib,host_memory_used_mib" >"$1"
  (
    while sleep 5; do
      gpu=$(nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader,nounits 2>/dev/null | head -1)
      echo "$(date +%T),${gpu:-,},$(free -m | awk '/^Mem:/{print $3}')"
    done
  ) >>"$1" &
  sampler=$!
}
