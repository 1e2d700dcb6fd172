#!/usr/bin/env bash
# The GPU check (issue 58), prepared so that a session lent a device spends its minutes measuring, not building.
# The device has CUDA and PyTorch but no Rust toolchain and no GDAL, so everything it runs is built here.
#
#   bash train/bench/device-check.sh prepare   # here: a release g2r-train with CUDA, the libraries it loads that
#                                              # are not glibc's, and a small dataset of the demo world
#                                              # (manifests/device.toml), packed into out/device/
#   bash train/bench/device-check.sh run       # on the device, e.g. through the device tool with carry
#                                              # ["out/device"]: writes every figure under $OUT (default out/device-check)
#
# `run` stops starting steps when its budget (BUDGET, 540 s) is spent, and caps each step's timeout to what is
# left, so it ends inside one 10-minute device command. In order of what matters most:
#   1. `bench --compare-conv-backward` at width 16, batch 8: Burn's convolution gradients against the rewritten
#      ones (kernels::cubecl), alternating, with the synced per-kernel split of each;
#   2. `bench --torch python3` at widths 16 and 8, alternating rounds with PyTorch;
#   3. a CubeCL profile of a few width-16 steps, kernel names and times (a cubecl.toml asks for its log on stderr);
#   4. a 500-step fit of the shipped recipe (H1, width 8, elevation + context, EMA) on cuda and on flex from the
#      same seed, `eval` of each on its own backend, and of the cuda run on flex.
# Settings: STEPS (500), BUDGET (540), BACKEND (cuda; `wgpu` or `flex` rehearse the script on a machine without a
# GPU, with the torch steps skipped unless TORCH is set; REHEARSAL=1 also shrinks every bench to width 4, batch 2,
# one step and one round, and the fits to 3 steps). For a rehearsal `prepare` takes G2R_TRAIN, a g2r-train already
# built (e.g. target/debug/g2r-train of a `--features wgpu` test build), instead of building, and MAX_MIB (64)
# for a debug binary's larger pack.
set -uo pipefail
[ -n "${G2R_TRAIN:-}" ] && G2R_TRAIN=$(realpath "$G2R_TRAIN")
[ -n "${OUT:-}" ] && mkdir -p "$OUT" && OUT=$(realpath "$OUT")
cd "$(dirname "$0")/../.."

PACK=out/device
mode=${1:-}

prepare() {
  set -e
  local binary=${G2R_TRAIN:-}
  if [ -z "$binary" ]; then
    cargo build --release --locked -p g2r-train --features cuda
    binary=target/release/g2r-train
  fi
  local data=out/device-dataset/dataset
  if [ ! -f "$data/manifest.json" ]; then
    [ -f out/demo-world/world.json ] ||
      cargo run --release --locked -p g2r-pipeline -- synth --preset demo --seed 42 --out out/demo-world --force
    cargo run --release --locked -p g2r-pipeline -- run manifests/device.toml
  fi
  rm -rf "$PACK" && mkdir -p "$PACK/stage/bin" "$PACK/stage/lib"
  strip -o "$PACK/stage/bin/g2r-train" "$binary"
  # Every shared library the binary loads except glibc's own (the device has a glibc at least as new).
  ldd "$binary" | awk '/=> \// {print $3}' | { grep -Ev '/(libc|libm|libpthread|libdl|librt|ld-linux[^/]*)\.so' || true; } |
    while read -r lib; do cp -L "$lib" "$PACK/stage/lib/"; done
  cp -r "$data" "$PACK/stage/data"
  tar -C "$PACK/stage" -cJf "$PACK/pack.tar.xz" bin lib data
  rm -rf "$PACK/stage"
  local mib=$(( $(stat -c %s "$PACK/pack.tar.xz") / 1048576 ))
  echo "device-check: $PACK/pack.tar.xz is ${mib} MiB (the device tool carries 64 MiB in all)" >&2
  [ "$mib" -lt "${MAX_MIB:-64}" ] || { echo "device-check: too large to carry: use a smaller dataset" >&2; exit 1; }
}

run() {
  local out=${OUT:-$PWD/out/device-check} backend=${BACKEND:-cuda} steps=${STEPS:-500} budget=${BUDGET:-540}
  local widths=(16 8) batch=8 iters=20 rounds=3
  if [ "${REHEARSAL:-0}" = 1 ]; then widths=(4) batch=2 iters=1 rounds=1 steps=3; fi
  local work=/tmp/g2r-device-check started=$SECONDS
  mkdir -p "$out" && rm -rf "$work" && mkdir -p "$work"
  tar -C "$work" -xJf "$PACK/pack.tar.xz" || { echo "device-check: no $PACK/pack.tar.xz: run 'prepare' first" >&2; exit 1; }
  export LD_LIBRARY_PATH="$work/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
  local g2r="$work/bin/g2r-train" data="$work/data" torch=${TORCH:-}
  [ "$backend" = cuda ] && torch=${TORCH:-python3}
  log() { echo "[$(date -u +%T) +$(( SECONDS - started ))s] $*" | tee -a "$out/steps.log" >&2; }
  step() { # step NAME TIMEOUT COMMAND...: stdout to $out/NAME.json, stderr to $out/NAME.log, status logged
    local name=$1 limit=$2 left=$(( budget - (SECONDS - started) )); shift 2
    if [ "$left" -lt 20 ]; then log "skip $name: the budget is spent"; return; fi
    [ "$limit" -le "$left" ] || limit=$left
    log "start $name (timeout ${limit}s)"
    timeout "$limit" "$@" >"$out/$name.json" 2>"$out/$name.log"
    log "end $name: exit $?"
  }
  { nvidia-smi -L; nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv; nproc; } >"$out/machine.txt" 2>&1
  [ -n "$torch" ] && "$torch" -c 'import torch; print("torch", torch.__version__, torch.cuda.is_available())' >>"$out/machine.txt" 2>&1

  local bench=("$g2r" bench --backend "$backend" --batch "$batch")
  step conv-backward-w"${widths[0]}" 150 "${bench[@]}" --width "${widths[0]}" --iters "$(( (iters + 1) / 2 ))" \
    --rounds "$rounds" --compare-conv-backward
  if [ -n "$torch" ]; then
    for width in "${widths[@]}"; do
      step bench-w"$width"-torch 120 "${bench[@]}" --width "$width" --iters "$iters" --rounds "$rounds" --torch "$torch"
    done
  fi
  # CubeCL reads cubecl.toml from the working directory: its profile log (kernel names and times) on stderr.
  mkdir -p "$work/profile" && printf '[profiling.logger]\nlevel = "medium"\nstderr = true\n' >"$work/profile/cubecl.toml"
  (cd "$work/profile" && step cubecl-profile-w"${widths[0]}" 60 "${bench[@]}" --width "${widths[0]}" --iters 2)
  gzip -f "$out/cubecl-profile-w${widths[0]}.log"

  local fit_args=(--data "$data" --model h1 --width 8 --batch "$batch" --epochs 100 --stop-after-steps "$steps"
    --max-val-samples 256 --lr 1e-3 --lr-schedule cosine --window 8 --no-dropout --elevation-input --context-input
    --ema 0.995 --seed 42)
  local runs=("$backend")
  [ "$backend" = flex ] || runs+=(flex)
  for run in "${runs[@]}"; do
    step fit-"$run" 180 "$g2r" fit --backend "$run" --out "$work/run-$run" "${fit_args[@]}"
    cp "$work/run-$run/metrics.jsonl" "$out/fit-$run-metrics.jsonl" 2>/dev/null
  done
  for run in "${runs[@]}"; do
    step eval-"$run" 90 "$g2r" eval --run "$work/run-$run" --data "$data" --backend "$run" --out "$work/eval-$run" --panels 0
    cp "$work/eval-$run/metrics.json" "$out/eval-$run-metrics.json" 2>/dev/null
  done
  if [ "$backend" != flex ]; then
    step eval-"$backend"-run-on-flex 90 "$g2r" eval --run "$work/run-$backend" --data "$data" --backend flex --out "$work/eval-cross" --panels 0
    cp "$work/eval-cross/metrics.json" "$out/eval-$backend-run-on-flex-metrics.json" 2>/dev/null
  fi
  log "done"
}

case "$mode" in
  prepare) prepare ;;
  run) run ;;
  *) echo "usage: bash train/bench/device-check.sh prepare|run (see the header)" >&2; exit 2 ;;
esac
