#!/usr/bin/env bash
# The paper-table runs (issue 27) on every local GPU: train each job at the paper's length and
# action repeat, export its agents, then evaluate it with the full protocol with both renderers side
# by side (the ray caster and the pool's exact look). One job per GPU at a time; job i runs on the
# (i mod G)-th of the G GPUs used.
#
#   benchmarks/paper_runs.sh OUT_DIR JOB [JOB ...]      JOB = task:aug[:seeds], e.g.
#   benchmarks/paper_runs.sh runs/paper walker-walk:drq cheetah-run:drq hopper-stand:drq finger-spin:drq
#   benchmarks/paper_runs.sh runs/paper walker-walk:cj+drq:0,1
#
# Run from the project root with the project importable (`python3 -m dmcr_jax.train` works) and
# MUJOCO_GL=egl. Per job it writes OUT_DIR/<task>-<aug>-s<seeds>/: run/ (train's folder), eval_jax/
# and eval_pool/ (evaluate's eval.json, .md, .png), agents/ (export_params), and one log per step.
# A step whose output exists is skipped, so calling it again after an interruption goes on where it
# stopped (an evaluation from its last finished condition); a job folder holding only agents/ (an
# export of a finished run, e.g. copied from another machine) is imported and evaluated.
# Environment: STEPS (override the paper's length, for a smoke test), TRAIN_ARGS and EVAL_ARGS
# (extra flags), POOL_EVAL_ARGS (the pool evaluation's alone, e.g. "--egl-devices 0,1" to draw its
# frames on two GPUs), SKIP_POOL=1 (ray-caster evaluation only), TRAIN_ONLY=1 (train and export
# only; call again without it to evaluate), GPU_IDS (the GPUs to use, e.g. "2 3"; default: all),
# WORKERS (render workers per job; default: the cores divided among the host's GPUs, at most 16).
set -uo pipefail
[ $# -ge 2 ] || { sed -n 2,9p "$0"; exit 2; }
OUT=$1; shift
mkdir -p "$OUT"
HOST_GPUS=$(nvidia-smi -L 2>/dev/null | wc -l); [ "$HOST_GPUS" -ge 1 ] || HOST_GPUS=1
read -r -a GPU_LIST <<< "${GPU_IDS:-$(seq -s ' ' 0 $(( HOST_GPUS - 1 )))}"
GPUS=${#GPU_LIST[@]}
for g in "${GPU_LIST[@]}"; do
  [[ "$g" =~ ^[0-9]+$ ]] && [ "$g" -lt "$HOST_GPUS" ] || {
    echo "GPU_IDS: $g is not one of this host's GPUs 0..$(( HOST_GPUS - 1 ))" >&2; exit 2; }
done
CORES=$(nproc)
WORKERS=${WORKERS:-$(( CORES / HOST_GPUS > 16 ? 16 : (CORES / HOST_GPUS > 1 ? CORES / HOST_GPUS : 1) ))}
PHYS=$(( WORKERS / 2 ))
steps_of() {
  python3 -c "from dmcr_jax.benchmarks.paper_table import TRAINING_STEPS as T; import sys; print(T[sys.argv[1]])" "$1"
}
# Refuse a bad job before anything starts.
for job in "$@"; do
  IFS=: read -r task aug seeds <<< "$job"
  [ -n "$aug" ] || { echo "job $job: want task:aug[:seeds]" >&2; exit 2; }
  [ -n "${STEPS:-}" ] || steps_of "$task" > /dev/null 2>&1 || {
    echo "job $job: $task is not one of the paper table's tasks" >&2; exit 2; }
done

run_job() {  # GPU JOB
  local gpu=$1 task aug seeds; IFS=: read -r task aug seeds <<< "$2"; seeds=${seeds:-0}
  local dir="$OUT/$task-${aug//+/}-s${seeds//,/_}" steps=${STEPS:-$(steps_of "$task")}
  mkdir -p "$dir"
  local on="env CUDA_VISIBLE_DEVICES=$gpu MUJOCO_EGL_DEVICE_ID=$gpu"
  [ "$HOST_GPUS" -gt 1 ] || on="env"
  # Agents exported on another machine (agents/ with its summary.json, no run/): import them,
  # so that the job goes straight on to its evaluations.
  if [ ! -f "$dir/run/summary.json" ] && [ ! -d "$dir/run/checkpoints" ] && [ -f "$dir/agents/summary.json" ]; then
    $on XLA_PYTHON_CLIENT_PREALLOCATE=false python3 -m dmcr_jax.benchmarks.export_params import \
      "$dir/agents" "$dir/run" > "$dir/import.log" 2>&1 \
      || { echo "$2: importing $dir/agents failed, see $dir/import.log" >&2; return 1; }
  fi
  if [ ! -f "$dir/run/summary.json" ]; then
    $on python3 -m dmcr_jax.train --task "$task" --aug "$aug" --seeds "$seeds" --steps "$steps" \
      --dtype bfloat16 --checkpoint-every 10000 --log-every 500 --no-progress \
      --workers "$WORKERS" --physics-workers "$PHYS" --out "$dir/run" \
      $( [ -d "$dir/run/checkpoints" ] && echo --resume ) ${TRAIN_ARGS:-} > "$dir/train.log" 2>&1 \
      || { echo "$2: training failed, see $dir/train.log" >&2; return 1; }
  fi
  [ -f "$dir/agents/config.json" ] || $on XLA_PYTHON_CLIENT_PREALLOCATE=false python3 -m dmcr_jax.benchmarks.export_params export \
      "$dir/run" "$dir/agents" > "$dir/export.log" 2>&1
  [ -z "${TRAIN_ONLY:-}" ] || { echo "$2: trained and exported ($dir)"; return 0; }
  # Both evaluations at once on the job's GPU, neither preallocating its memory: the ray
  # caster's is GPU compute, the pool's mostly waits on its render workers' frames.
  local ev="$on XLA_PYTHON_CLIENT_PREALLOCATE=false"
  [ -f "$dir/eval_jax/eval.json" ] || $ev python3 -m dmcr_jax.train.evaluate "$dir/run" \
      --renderer jax --no-progress --out "$dir/eval_jax" ${EVAL_ARGS:-} > "$dir/eval_jax.log" 2>&1 &
  [ -n "${SKIP_POOL:-}" ] || [ -f "$dir/eval_pool/eval.json" ] || $ev python3 -m dmcr_jax.train.evaluate \
      "$dir/run" --workers "$WORKERS" --no-progress --out "$dir/eval_pool" ${EVAL_ARGS:-} ${POOL_EVAL_ARGS:-} \
      > "$dir/eval_pool.log" 2>&1 &
  wait
  for r in jax pool; do
    [ "$r" = pool ] && [ -n "${SKIP_POOL:-}" ] && continue
    [ -f "$dir/eval_$r/eval.json" ] || { echo "$2: $r evaluation failed, see $dir/eval_$r.log" >&2; return 1; }
  done
  echo "$2: done ($dir)"
}

gpu_queue() {  # SLOT: the jobs i with i mod GPUS == SLOT, one after the other, on GPU_LIST[SLOT]
  local slot=$1 i=0; shift
  for job in "$@"; do
    [ $(( i % GPUS )) -eq "$slot" ] && run_job "${GPU_LIST[$slot]}" "$job"
    i=$(( i + 1 ))
  done
}

for (( g = 0; g < GPUS; g++ )); do gpu_queue "$g" "$@" & done
wait
