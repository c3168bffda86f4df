#!/usr/bin/env bash
# The GPU-box sweep whose results are committed in benchmarks/results/*_h100.*.
# Run from the project root on the GPU machine (the project installed, so that
# `python3 -m dmcr_jax.benchmarks.x` imports; mujoco, MJX, dm_control importable;
# MUJOCO_GL=egl). Every benchmark appends to its JSONL and skips what is there, so
# calling this again after a time limit resumes the sweep. BUDGET_S bounds the
# wall time of the long all-task physics sweep (default 540 s from the start).
set -uo pipefail
R=benchmarks/results
BUDGET_S=${BUDGET_S:-540}
mkdir -p "$R"
have() { [ -s "$R/$1" ]; }

# 1. The walker target: task vs bare MJX at 1…8,192 envs, dm_control's solver budget,
#    then with mjx.benchmark's budget (1 solver / 4 line-search iterations).
python3 -m dmcr_jax.benchmarks.physics --tasks walker-walk --sizes 1,64,1024,8192 \
  --parallel-compiles 8 --out $R/physics_h100.jsonl
python3 -m dmcr_jax.benchmarks.physics --tasks walker-walk,cartpole-swingup,hopper-hop,cheetah-run \
  --sizes 8192 --solver-iterations 1 --ls-iterations 4 --parallel-compiles 8 \
  --tasks-per-wave 4 --out $R/physics_h100_solver1.jsonl
# 1b. Line-search caps (dm_control's solver iterations): what the MJX scan costs.
for ls in 16 8 4; do
  python3 -m dmcr_jax.benchmarks.physics --tasks walker-walk --sizes 8192 --ls-iterations $ls \
    --parallel-compiles 2 --out $R/physics_h100_budgets.jsonl
done
# 2. Augmentations (jitted, 256×84×84×9 batches).
have augment_h100.jsonl || python3 -m dmcr_jax.benchmarks.augment --out $R/augment_h100.jsonl
# 3. The render pool against the naive one-Renderer loop, EGL.
have render_h100.jsonl || python3 -m dmcr_jax.benchmarks.render --batches 1024,4096 --workers 4,16 \
  --qualities exact,fast,fastest --out $R/render_h100.jsonl
# 3b. Which part of the tiled render loop limits the pool.
have render_variants_h100.jsonl || python3 -m dmcr_jax.benchmarks.render_variants --procs 1,4,16 \
  --out $R/render_variants_h100.jsonl
# 3c. The pixel env (walker-walk, frame skip 2) against the original dm_control pipeline.
have env_h100.jsonl || python3 -m dmcr_jax.benchmarks.env --sizes 1024,256,16,1 --qualities fastest \
  --out $R/env_h100.jsonl
# 4. Every task at every size (task wrapper only), as far as the budget allows.
#    Autotuning off: concurrent compiles otherwise queue on the GPU autotuner.
left=$((BUDGET_S - SECONDS))
[ "$left" -gt 60 ] && XLA_FLAGS=--xla_gpu_autotune_level=0 timeout "$left" \
  python3 -m dmcr_jax.benchmarks.physics --tasks all --sizes 1,64,1024,8192 --no-baseline \
  --steps 10 --repeats 3 --parallel-compiles 8 --tasks-per-wave 2 ${SWEEP_ARGS:-} \
  --out $R/physics_h100${SWEEP_SUFFIX:-}.jsonl
exit 0
