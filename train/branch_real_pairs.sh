#!/usr/bin/env bash
# Fine-tune a Local-ScaleNet campaign checkpoint on the campaign's synthetic pairs plus the real-pair labels of
# the shared photo collections, leaving one collection out (validated on it).
#   train/branch_real_pairs.sh INIT HELD_OUT OUT [extra localscale-train options]
# INIT: a checkpoint (runs/campaign_local/last.pt or a copy); HELD_OUT: a collection folder name;
# labels: runs/real_models/<collection>/pairs.npz from train/label_collections.py (LABELS overrides the folder).
# Resumes from OUT/last.pt with the same command.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ $# -lt 3 ]; then echo "usage: $0 INIT HELD_OUT OUT [options]" >&2; exit 2; fi
INIT=$1; HELD=$2; OUT=$3; shift 3
LABELS=${LABELS:-runs/real_models}
[ -f "$INIT" ] || { echo "error: no checkpoint $INIT" >&2; exit 2; }
[ -f "$LABELS/$HELD/pairs.npz" ] || { echo "error: no labels $LABELS/$HELD/pairs.npz" >&2; exit 2; }
TRAIN=$(for d in "$LABELS"/*/; do n=$(basename "$d"); [ "$n" != "$HELD" ] && [ -f "$d/pairs.npz" ] && echo "$d""pairs.npz"; done | paste -sd,)
OMP_NUM_THREADS=1 exec localscale-train --model local --data ../shared/data/train_images --out "$OUT" \
  --context --crop-min 0.4 --perspective 0.7 --scale-min 0.125 --scale-max 8 \
  --identity-probability 0.1 --full-rotation-probability 0.5 --low-overlap-probability 0.15 \
  --unrelated-probability 0.05 --gray-one-side-probability 0.1 --strong-light-probability 0.2 \
  --degrade-probability 0.15 --swap-probability 0.3 --topk 32 --warp-features --visibility \
  --loss-per-pair --batch-size 8 --threads 1 --workers 0 --seed 31 --init-weights "$INIT" \
  --real-pairs "$TRAIN" --real-fraction 0.3 --real-val-pairs "$LABELS/$HELD/pairs.npz" \
  --steps 2000 --lr 5e-5 --lr-milestones 1600 --val-every 500 --ckpt-every 100 "$@"
