#!/bin/bash
# Worlds and scores of the many-craters recipe (issue 62), from the release binaries (cargo build --release --workspace
# --bins). Each world is the preset `many-craters` at a seed; its manifest is manifests/many-craters.toml with the
# seed, paths and name changed, written beside the world.
#
#   many_craters.sh publish OUT SEED train   a training world: framed by 8 error draws of its catalogue (the manifest's),
#                                            at coverage $TRAIN_COVERAGE (default 9.65, half the manifest's 19.3:
#                                            the fit draws 32,000 samples, so six worlds at half weigh alike and fit
#                                            the disk)
#   many_craters.sh publish OUT SEED exact   a validation world: framed by its exact catalogue
#   many_craters.sh train OUT RUN VAL SEED...  the recipe trained across the training worlds SEED... (each published
#                                            with `publish OUT SEED train`; the first is --data, the rest
#                                            --also-train-on) and validated on their held-out tiles and on world
#                                            VAL (published `exact`); run again after a stop and it resumes.
#                                            FIT_FLAGS="..." adds flags to the recipe for a trial. No crater level:
#                                            on world 4's validation tiles it made the wall and rim worse than the
#                                            network alone (docs/experiments.md, thirty-eighth session)
#   many_craters.sh demo OUT RUN             the demo world (preset demo, seed 42) with the many-craters preset's unit map,
#                                            framed by its one complex crater (manifests/demo-craters.csv; 5 km, under
#                                            the training worlds' 8.3-14 km, so the frame's minimum diameter is lowered
#                                            to 4 km) and published as a test world; RUN scored on all its test crops,
#                                            framed and not: OUT/demo/eval-RUNNAME-{exact,unframed}
#   many_craters.sh test OUT SEED RUN [N]    a test world, published three times from the same crops (framed by its
#                                            exact catalogue, a perturbed one and one listing a phantom 18 km crater:
#                                            docs/scripts/catalogue_variants.py), and RUN scored on N spread test
#                                            crops (default 4096) of each, and on the exact one without crater frames;
#                                            the scores go to OUT/eval-RUNNAME-world-SEED-{exact,unframed,perturbed,phantom}
#
# A test world differs from a training world's publication only in size: coverage 4 (not 19.3) and 85 % of its tiles in
# test (5 % val, 10 % train, where the honest Hapke scale's calibration crops come from), since nothing trains on it.
# Each step is skipped when its output exists; the pipeline's stages/ are deleted after publication, for disk (a
# world is ~10 GB, a training publication ~3 GB at half coverage). Timings go to OUT/*.time (/usr/bin/time -v).
set -euo pipefail
repo=$(cd "$(dirname "$0")/../.." && pwd)
bin=$repo/target/release
python=${PYTHON:-$repo/.venv/bin/python3}
mode=$1; out=$2; seed=$3
mkdir -p "$out"
cd "$out"

world() {
  if [ ! -f world-$seed/world.json ]; then
    /usr/bin/time -v "$bin/g2r-pipeline" synth --preset many-craters --seed "$seed" --out world-$seed \
      > world-$seed.log 2> world-$seed.time
  fi
}

# manifest NAME CATALOGUE DATASET_DIR [sed expressions...]: the preset's manifest for this world.
manifest() {
  local name=$1 catalogue=$2 dataset=$3
  shift 3
  sed -e "s#\.\./out/many-craters-world/truth/complex_craters.csv#$catalogue#" \
      -e "s#\.\./out/many-craters-world#world-$seed#g" -e "s#\.\./out/many-craters-dataset#$dataset#" \
      -e "s/^seed = 42/seed = $seed/" -e "s/^name = \"g2r-many-craters\"/name = \"$name\"/" "$@" \
      "$repo/manifests/many-craters.toml" > manifest-$dataset.toml
}

publish() { # DATASET_DIR
  if [ ! -f $1/dataset/manifest.json ]; then
    /usr/bin/time -v "$bin/g2r-pipeline" run manifest-$1.toml > $1.log 2> $1.time
    rm -rf $1/stages
  fi
}

# The recipe: the shipped one (train/shipped/README.md) with heights relative to the crop and its surroundings only
# (no --elevation-input: a new site's datum is not the training worlds'), the crater frame as an input, with the
# framing crater's relief over diameter (how worn it is), and the site's mare/highland unit map; crops of mean slope
# at least 20° drawn three times as often (--steep-weight 3: a quarter of the crops, where the crater walls are).
recipe=(--model h1 --width 8 --batch 8 --epochs 2 --max-train-samples 32000 --max-val-samples 1024 --lr 1e-3
  --lr-schedule cosine --window 8 --no-dropout --context-input --crater-input --crater-frame-input --crater-relief-input
  --unit-input --steep-weight 3 --ema 0.995 --seed 42)
read -r -a trial <<< "${FIT_FLAGS:-}"

case $mode in
  train)
    run=$3; val=$4; shift 4
    [ $# -ge 1 ] || { echo "train: name at least one training seed" >&2; exit 2; }
    first=$1; shift
    pooled=()
    for s in "$@"; do pooled+=(--also-train-on data-$s/dataset); done
    resume=()
    [ -f "$run/config.json" ] && resume=(--resume)
    /usr/bin/time -v "$bin/g2r-train" fit --data data-$first/dataset "${pooled[@]}" --also-validate-on data-$val/dataset \
      --out "$run" "${recipe[@]}" "${trial[@]}" "${resume[@]}" >> "$run.log" 2>> "$run.time"
    ;;
  publish)
    role=$4
    world
    case $role in
      train) manifest g2r-many-craters-$seed world-$seed/truth/complex_craters.csv data-$seed \
               -e "s/^coverage = .*/coverage = ${TRAIN_COVERAGE:-9.65}/" ;;
      exact) manifest g2r-many-craters-$seed world-$seed/truth/complex_craters.csv data-$seed \
               -e '/^crater_catalogue_error = /d' ;;
      *) echo "publish: role must be train or exact, not $role" >&2; exit 2 ;;
    esac
    publish data-$seed
    ;;
  test)
    run=$4; samples=${5:-4096}
    world
    mkdir -p catalogues-$seed
    cp world-$seed/truth/complex_craters.csv catalogues-$seed/exact.csv
    "$python" "$repo/docs/scripts/catalogue_variants.py" world-$seed catalogues-$seed > catalogues-$seed/variants.txt
    for variant in exact perturbed phantom; do
      manifest g2r-many-craters-$seed-$variant catalogues-$seed/$variant.csv test-$seed-$variant \
        -e "s|# the drawn craters, exact|# $variant: docs/scripts/catalogue_variants.py|" \
        -e '/^crater_catalogue_error = /d' -e 's/^coverage = .*/coverage = 4.0/' \
        -e 's/^val_fraction = .*/val_fraction = 0.05/' -e 's/^test_fraction = .*/test_fraction = 0.85/'
      publish test-$seed-$variant
    done
    score() { # NAME DATASET_VARIANT [eval flags...]
      # Beside the worlds, not in RUN: a shipped run directory stays as it shipped.
      local scored=eval-$(basename "$run")-world-$seed-$1
      if [ ! -f $scored/metrics.json ]; then
        /usr/bin/time -v "$bin/g2r-train" eval --run "$run" --data test-$seed-$2/dataset --world world-$seed \
          --max-samples "$samples" --out $scored "${@:3}" > $scored.log 2> $scored.time
      fi
    }
    score exact exact
    score unframed exact --without-crater-frames
    score perturbed perturbed
    score phantom phantom
    ;;
  demo)
    run=$3
    case $run in /*) ;; *) run=../$run ;; esac  # from OUT/demo
    mkdir -p demo
    cd demo
    if [ ! -f world/world.json ]; then
      { cat "$repo/manifests/world-demo.toml"
        sed -n '/^\[unit_map\]/,/^displacement_wavelength_m/p' "$repo/manifests/world-many-craters.toml"
      } > world-demo-units.toml
      "$bin/g2r-pipeline" synth --config world-demo-units.toml --seed 42 --out world > world.log 2>&1
    fi
    sed -e 's#\.\./out/demo-world#world#g' -e 's#\.\./out/demo-dataset#dataset#' \
        -e "s|^# crater_catalogue = .*|crater_catalogue = \"$repo/manifests/demo-craters.csv\"|" \
        -e 's|^# unit_map = .*|unit_map = "world/map/units.tif"|' \
        -e 's/^context_gsd_m = .*/&\ncrater_frame_min_diameter_m = 4000.0/' \
        -e 's/^val_fraction = .*/val_fraction = 0.05/' -e 's/^test_fraction = .*/test_fraction = 0.85/' \
        "$repo/manifests/demo.toml" > manifest-dataset.toml
    publish dataset
    for variant in exact unframed; do
      scored=eval-$(basename "$run")-$variant
      flags=()
      [ $variant = unframed ] && flags=(--without-crater-frames)
      if [ ! -f $scored/metrics.json ]; then
        "$bin/g2r-train" eval --run "$run" --data dataset/dataset --split test --world world --out $scored \
          "${flags[@]}" > $scored.log 2>&1
      fi
    done
    ;;
  *) echo "usage: many_craters.sh publish OUT SEED train|exact | train OUT RUN VAL SEED... | test OUT SEED RUN [N] | demo OUT RUN" >&2; exit 2 ;;
esac
