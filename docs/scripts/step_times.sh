#!/bin/bash
# Step time of the shipped recipe at widths 4, 8 and 16 (docs/results/36-speed-vs-error.json): short fits, run alone on the
# cores; fit logs samples/s once a minute, so each trains for more than a minute.
cd "$(dirname "$0")/../.."
mkdir -p out/speed
for spec in "4 6000" "8 3600" "16 1800"; do
  set -- $spec
  /usr/bin/time -v target/release/g2r-train fit --data out/tycho-dataset/dataset --out out/speed/w$1 --model h1 --width $1 --batch 8 --epochs 1 --max-train-samples $2 --max-val-samples 8 --lr 1e-3 --lr-schedule cosine --window 8 --no-dropout --elevation-input --context-input --ema 0.995 --seed 42 > out/speed/w$1.log 2>&1
done
