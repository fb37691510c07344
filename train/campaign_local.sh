#!/usr/bin/env bash
# The Local-ScaleNet training campaign: one long run, resumed each session from runs/campaign_local/last.pt,
# or from the committed copy in train/campaign/local/ when that is ahead (a fresh clone). Same command to resume;
# before committing: python train/campaign.py pack. Extra options pass through (e.g. --device cuda; keep the batch size: the data is indexed by it).
set -euo pipefail
cd "$(dirname "$0")/.."
python train/campaign.py unpack
OMP_NUM_THREADS=1 exec localscale-train --model local --data ../shared/data/train_images --out runs/campaign_local \
  --context --crop-min 0.4 --perspective 0.7 --scale-min 0.125 --scale-max 8 \
  --identity-probability 0.1 --full-rotation-probability 0.5 --low-overlap-probability 0.15 \
  --unrelated-probability 0.05 --gray-one-side-probability 0.1 --strong-light-probability 0.2 \
  --degrade-probability 0.15 --swap-probability 0.3 --topk 32 --warp-features --visibility \
  --loss-per-pair --batch-size 8 --threads 1 --workers 0 --seed 23 \
  --init-weights localscale/weights/local_scalenet.pt \
  --steps 60000 --lr 1e-4 --lr-milestones 45000 55000 --val-every 1000 --ckpt-every 200 "$@"
