#!/bin/bash
# Train the paper preset on a lent GPU and time its inference, in one call (docs/training.md, 'On a lent GPU').
#
# Run from the repository root on the lent machine, with the compact data copy and the missing wheels carried:
#   carry: .whl (diffusers, gymnasium, farama-notifications, importlib_metadata), data/train16k_paper
#   env:   PARCELPICK_GIT_COMMIT  the commit the tree was sent at (what git finds there can be older)
#          STEPS                  optimisation steps; unset: a 30-step timing run sizes them to TRAIN_S seconds
#          TRAIN_S (330), MAX_MIN (6.5), DATA (data/train16k_paper), EXTRA (more train flags: --segment-levers)
# Writes to $OUT: gpu.txt, train.log, log.jsonl, config.json, paper_last.pt, paper_best.pt (weights only), latency.md.
set -uo pipefail
: "${OUT:?set OUT to the folder that comes back}" "${PARCELPICK_GIT_COMMIT:?name the commit the tree was sent at}"
t0=$(date +%s)
say() { echo "[$(( $(date +%s) - t0 )) s] $*"; }
if compgen -G ".whl/*.whl" > /dev/null; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 3
fi
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 PARCELPICK_GIT_COMMIT
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv | tee "$OUT/gpu.txt"
echo "cpus $(nproc)" | tee -a "$OUT/gpu.txt"
python3 -c "import sys, torch, policies.diffusion.train; print('torch', torch.__version__, torch.cuda.is_available());
sys.exit(0 if torch.cuda.is_available() else 1)" 2>&1 | tee -a "$OUT/gpu.txt" || { echo "no CUDA here"; exit 4; }
DATA=${DATA:-data/train16k_paper}
COMMON="--data $DATA --preset paper --batch-size 16 --lr 1e-3 --seed 0 --device cuda --threads 4 --workers 12
  --label-set paper --no-progress ${EXTRA:-}"
if [ -z "${STEPS:-}" ]; then
  python3 -m policies.diffusion.train $COMMON --out /tmp/cal --steps 30 --val-every 1000 --val-scenes 2 \
    > /tmp/cal.log 2>&1 || { tail -30 /tmp/cal.log; exit 5; }
  SPS=$(python3 -c "import json; print([json.loads(l) for l in open('/tmp/cal/log.jsonl')][-1]['sec_per_step'])")
  STEPS=$(python3 -c "print(max(100, int(${TRAIN_S:-330} / $SPS) // 50 * 50))")
  say "timed: $SPS s a step at batch 16; training $STEPS steps"
fi
python3 -m policies.diffusion.train $COMMON --out /tmp/paper --steps "$STEPS" --val-every $(( STEPS / 4 )) \
  --val-scenes 16 --max-minutes "${MAX_MIN:-6.5}" > "$OUT/train.log" 2>&1
say "trained (exit $?)"; grep -v "^train" "$OUT/train.log" | tail -8
cp /tmp/paper/log.jsonl /tmp/paper/config.json "$OUT/"
python3 -m policies.diffusion.checkpoint /tmp/paper/last.pt "$OUT/paper_last.pt" --note "paper preset, lent GPU, $STEPS steps"
if [ -f /tmp/paper/best.pt ]; then
  python3 -m policies.diffusion.checkpoint /tmp/paper/best.pt "$OUT/paper_best.pt" --note "paper preset, lent GPU, best"
fi
say "exported"
python3 benchmarks/bench_diffusion.py --device cuda --checkpoint "$OUT/paper_last.pt" --threads 2 --repeats 10 \
  2>&1 | tee "$OUT/latency.md"
say "done"
