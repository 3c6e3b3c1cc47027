#!/usr/bin/env bash
# Train every shipped model from a clean checkout, exactly as the committed weights were made
# (docs/MODEL.md, "Shipped models"): stage 1 on the source split (our-1, our-1-resnet), stage 2 adapted to each
# benchmark's target domain (our-3-boreas, our-3-loop, our-3-offroad, our-3-boreas-resnet). A model adapted to
# one domain is the "Our (2)" cross-domain setting on the others. The simulator renders the training splits into the cache first.
#
#   bash scripts/train_models.sh            # all ten models, in dependency order (width 0.5 first)
#   bash scripts/train_models.sh our-1 our-3-boreas     # just these (stage 2 needs its stage-1 model)
#
# Step counts, not wall-clock budgets, end every run, so the same command gives the same weights on one machine
# (1 torch thread, seed 0; bit-identical on the same CPU instruction set and torch build - another machine drifts
# in the last digits, docs/MODEL.md). On the 2-core CPU: stage 1 ~22 min, each stage 2 ~7 min when run alone.
# Stage 2 ends with learned whitening of the projection (--learned-whitening: matching pairs of the split's own
# training scans; docs/MODEL.md, "Learned whitening"); a run that resumes a finished checkpoint only re-fits it.
# Defaults of `reradar train` used here (docs/MODEL.md): NetVLAD over the sensor disc only (ModelConfig.disc_mask,
# on; --no-disc-mask turns it off) and random in-batch negatives (hard negatives from a memory bank,
# --hard-negatives N, did not win on validation and stay opt-in; so does --rotation-consistency W, session 37). A checkpoint resumes only when it records the
# same training settings, --init weights and data (checkpoints written before session 23 record none and are
# refused): run with FRESH=1 to retrain from scratch.
# Weights go to reradar_core/model/weights/ unless OUT_DIR is set; runs resume from their checkpoints
# unless FRESH=1.
set -euo pipefail
cd "$(dirname "$0")/.."
export OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1

STAGE1_STEPS=3000   # stage 1 (source domain, from random weights), lr 1e-3
STAGE2_STEPS=800    # stage 2 (adaptation from a stage-1 model), lr 1e-4

extra=(--overwrite)   # retraining replaces the shipped weights of the same name
[[ -n "${OUT_DIR:-}" ]] && extra+=(--out-dir "$OUT_DIR")
[[ "${FRESH:-0}" == "1" ]] && extra+=(--no-resume)
if [[ -n "${OUT_DIR:-}" ]]; then init_dir="$OUT_DIR/"; else init_dir=""; fi
init() { if [[ -n "$init_dir" ]]; then echo "${init_dir}$1.pt"; else echo "$1"; fi; }

train_one() {
  case "$1" in
    our-1)
      reradar train --name our-1 --split train-source --lr 1e-3 --steps "$STAGE1_STEPS" --minutes 600 "${extra[@]}" ;;
    our-1-resnet)
      reradar train --name our-1-resnet --backbone resnet --split train-source --lr 1e-3 \
        --steps "$STAGE1_STEPS" --minutes 600 "${extra[@]}" ;;
    our-3-boreas)
      reradar train --name our-3-boreas --split train-target-boreas --init "$(init our-1)" --lr 1e-4 \
        --steps "$STAGE2_STEPS" --minutes 600 --learned-whitening "${extra[@]}" ;;
    our-3-loop)
      reradar train --name our-3-loop --split train-target-loop,train-target-loop-open --init "$(init our-1)" --lr 1e-4 \
        --steps "$STAGE2_STEPS" --minutes 600 --learned-whitening "${extra[@]}" ;;
    our-3-offroad)
      reradar train --name our-3-offroad --split train-target-offroad --init "$(init our-1)" --lr 1e-4 \
        --steps "$STAGE2_STEPS" --minutes 600 --learned-whitening "${extra[@]}" ;;
    our-3-boreas-resnet)
      reradar train --name our-3-boreas-resnet --backbone resnet --split train-target-boreas \
        --init "$(init our-1-resnet)" --lr 1e-4 --steps "$STAGE2_STEPS" --minutes 600 --learned-whitening "${extra[@]}" ;;
    # width 0.5 (F' C = 32; docs/MODEL.md, "Width 0.5, measured"): the suites' target-adapted models and the service
    # default (our-3-boreas-w05) since session 16; stage 1 ~51 min, each stage 2 ~13-15 min alone on the 2-core CPU
    our-1-w05)
      reradar train --name our-1-w05 --split train-source --lr 1e-3 --steps "$STAGE1_STEPS" --minutes 600 \
        --width 0.5 "${extra[@]}" ;;
    our-3-boreas-w05|our-3-loop-w05|our-3-offroad-w05)
      local split
      case "$1" in
        our-3-boreas-w05) split=train-target-boreas ;;
        our-3-loop-w05) split=train-target-loop,train-target-loop-open ;;
        our-3-offroad-w05) split=train-target-offroad ;;
      esac
      reradar train --name "$1" --split "$split" --init "$(init our-1-w05)" --lr 1e-4 --steps "$STAGE2_STEPS" \
        --minutes 600 --width 0.5 --learned-whitening "${extra[@]}" ;;
    *) echo "unknown model $1 (choose: our-1 our-1-resnet our-3-boreas our-3-loop our-3-offroad our-3-boreas-resnet;" \
            "width 0.5: our-1-w05 our-3-boreas-w05 our-3-loop-w05 our-3-offroad-w05)" >&2
       exit 2 ;;
  esac
}

models=("$@")
[[ ${#models[@]} -eq 0 ]] && models=(our-1-w05 our-3-boreas-w05 our-3-loop-w05 our-3-offroad-w05
                                     our-1 our-1-resnet our-3-boreas our-3-loop our-3-offroad our-3-boreas-resnet)
for m in "${models[@]}"; do
  echo "== training $m"
  train_one "$m"
done
