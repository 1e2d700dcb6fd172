#!/usr/bin/env bash
# The GPU check (issue 58), prepared so that a session lent a device spends its minutes measuring, not building.
# The device has CUDA and PyTorch but no Rust toolchain and no GDAL, so everything it runs is built here.
#
#   bash train/bench/device-check.sh prepare   # here: a release g2r-train with CUDA, the libraries it loads that
#                                              # are not glibc's, and a demo dataset, packed into out/device/
#   bash train/bench/device-check.sh run       # on the device, e.g. through the device tool with carry
#                                              # ["out/device"]: writes every figure under $OUT (default out/device-check)
#
# `run` takes under 10 minutes of an H200 (every step has its own timeout) and does, in order:
#   1. `bench --backend cuda --torch python3` at widths 16 and 8 (batch 8), alternating rounds with PyTorch;
#   2. `bench --compare-conv-backward` at width 16: the stock against the matmul weight gradients, alternating;
#   3. the per-kernel split (synced) from the bench reports, and a CubeCL profile (CUBECL_DEBUG_OPTION=profile);
#   4. a 500-step fit of the shipped recipe (H1, width 8, elevation + context, EMA) on cuda and on flex from the
#      same seed, then `eval` of each run on its own backend and of the cuda run on flex.
# Settings: STEPS (500), FIT_TIMEOUT (240 s per fit), BACKEND (cuda; `wgpu` or `flex` rehearse the script on a
# machine without a GPU, with the torch steps skipped unless TORCH is set). For such a rehearsal `prepare` takes
# FEATURES (cuda) and PROFILE (release; `dev` reuses a test build's binary).
set -uo pipefail
cd "$(dirname "$0")/../.."

PACK=out/device
mode=${1:-}

prepare() {
  set -e
  local profile=${PROFILE:-release} features=${FEATURES:-cuda}
  local target_dir=target/$([ "$profile" = dev ] && echo debug || echo "$profile")
  cargo build --profile "$profile" --locked -p g2r-train --features "$features"
  local data=out/demo-dataset/dataset
  if [ ! -f "$data/manifest.json" ]; then
    cargo run --profile "$profile" --locked -p g2r-pipeline -- synth --preset demo --seed 42 --out out/demo-world --force
    cargo run --profile "$profile" --locked -p g2r-pipeline -- run manifests/demo.toml
  fi
  rm -rf "$PACK" && mkdir -p "$PACK/stage/bin" "$PACK/stage/lib"
  strip -o "$PACK/stage/bin/g2r-train" "$target_dir/g2r-train"
  # Every shared library the binary loads except glibc's own (the device has a glibc at least as new).
  ldd "$target_dir/g2r-train" | awk '/=> \// {print $3}' |
    grep -Ev '/(libc|libm|libpthread|libdl|librt|ld-linux[^/]*)\.so' |
    while read -r lib; do cp -L "$lib" "$PACK/stage/lib/"; done
  cp -r "$data" "$PACK/stage/data"
  tar -C "$PACK/stage" -cJf "$PACK/pack.tar.xz" bin lib data
  rm -rf "$PACK/stage"
  local mib=$(( $(stat -c %s "$PACK/pack.tar.xz") / 1048576 ))
  echo "device-check: $PACK/pack.tar.xz is ${mib} MiB (the device tool carries 64 MiB in all)" >&2
  [ "$mib" -lt 64 ] || { echo "device-check: too large to carry: use a smaller dataset" >&2; exit 1; }
}

run() {
  local out=${OUT:-out/device-check} backend=${BACKEND:-cuda} steps=${STEPS:-500}
  local fit_timeout=${FIT_TIMEOUT:-240} work=/tmp/g2r-device-check
  mkdir -p "$out" && rm -rf "$work" && mkdir -p "$work"
  tar -C "$work" -xJf "$PACK/pack.tar.xz" || { echo "device-check: no $PACK/pack.tar.xz: run 'prepare' first" >&2; exit 1; }
  export LD_LIBRARY_PATH="$work/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
  local g2r="$work/bin/g2r-train" data="$work/data" torch=${TORCH:-}
  [ "$backend" = cuda ] && torch=${TORCH:-python3}
  log() { echo "[$(date -u +%T)] $*" | tee -a "$out/steps.log" >&2; }
  step() { # step NAME TIMEOUT COMMAND...: stdout to $out/NAME.json, stderr to $out/NAME.log, status logged
    local name=$1 limit=$2; shift 2
    log "start $name"
    timeout "$limit" "$@" >"$out/$name.json" 2>"$out/$name.log"
    log "end $name: exit $?"
  }
  { nvidia-smi -L; nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv; nproc; } >"$out/machine.txt" 2>&1
  [ -n "$torch" ] && "$torch" -c 'import torch; print("torch", torch.__version__, torch.cuda.is_available())' >>"$out/machine.txt" 2>&1

  if [ -n "$torch" ]; then
    step bench-w16-torch 150 "$g2r" bench --backend "$backend" --width 16 --batch 8 --iters 20 --rounds 3 --torch "$torch"
    step bench-w8-torch 120 "$g2r" bench --backend "$backend" --width 8 --batch 8 --iters 20 --rounds 3 --torch "$torch"
  fi
  step conv-backward-w16 150 "$g2r" bench --backend "$backend" --width 16 --batch 8 --iters 10 --rounds 2 --compare-conv-backward
  CUBECL_DEBUG_OPTION=profile step cubecl-profile-w16 90 "$g2r" bench --backend "$backend" --width 16 --batch 8 --iters 3
  gzip -f "$out/cubecl-profile-w16.log"

  local fit_args=(--data "$data" --model h1 --width 8 --batch 8 --epochs 100 --stop-after-steps "$steps"
    --max-val-samples 256 --lr 1e-3 --lr-schedule cosine --window 8 --no-dropout --elevation-input --context-input
    --ema 0.995 --seed 42)
  step fit-"$backend" "$fit_timeout" "$g2r" fit --backend "$backend" --out "$work/run-$backend" "${fit_args[@]}"
  [ "$backend" = flex ] || step fit-flex "$fit_timeout" "$g2r" fit --backend flex --out "$work/run-flex" "${fit_args[@]}"
  for run in "$backend" flex; do
    cp "$work/run-$run/metrics.jsonl" "$out/fit-$run-metrics.jsonl" 2>/dev/null
    step eval-"$run" 120 "$g2r" eval --run "$work/run-$run" --data "$data" --backend "$run" --out "$work/eval-$run" --panels 0
    cp "$work/eval-$run/metrics.json" "$out/eval-$run-metrics.json" 2>/dev/null
  done
  if [ "$backend" != flex ]; then
    step eval-"$backend"-run-on-flex 120 "$g2r" eval --run "$work/run-$backend" --data "$data" --backend flex --out "$work/eval-cross" --panels 0
    cp "$work/eval-cross/metrics.json" "$out/eval-$backend-run-on-flex-metrics.json" 2>/dev/null
  fi
  log "done"
}

case "$mode" in
  prepare) prepare ;;
  run) run ;;
  *) echo "usage: bash train/bench/device-check.sh prepare|run (see the header)" >&2; exit 2 ;;
esac
