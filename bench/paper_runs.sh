#!/usr/bin/env bash
# The paper-scale runs of results/paper/, one phase per call so that each fits a 10-minute job on one GPU.
# Usage: bash bench/paper_runs.sh PHASE   (PHASE: bench | digit-a | digit-b | transfer)
# Artifacts go to $TNF_DATA (default /tmp/tnf-paper); timings and reports are copied to $OUT when it is set.
set -euo pipefail
export TNF_DATA=${TNF_DATA:-/tmp/tnf-paper} PYTHONUNBUFFERED=1
out=${OUT:-$TNF_DATA/out}
mkdir -p "$out"
tnf() { python -m tnf.cli "$@"; }
common=(experiment=sim_digit device=cuda trainer=gpu progress=false)
case "$1" in
  bench)
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv | tee "$out/hardware.txt"
    python -c "import torch, warp, lightning; print('torch', torch.__version__, 'warp', warp.__version__, 'lightning', lightning.__version__)" | tee -a "$out/hardware.txt"
    python bench/sim.py --device cuda --batch 512 2>&1 | tee "$out/bench_sim_cuda.txt"
    python bench/capture.py --device cuda 2>&1 | tee "$out/bench_capture_gpu.txt"
    ;;
  digit-a)   # objects -> views -> scenes -> touches
    for s in capture fit-scene touch; do
      t0=$SECONDS; tnf "$s" "${common[@]}"; echo "stage $s: $((SECONDS - t0)) s"
    done 2>&1 | tee "$out/digit_a.log"
    ;;
  digit-b)   # pairs -> generator -> generated touches -> report (one seed)
    tnf pipeline "${common[@]}" 2>&1 | tee "$out/digit_b.log"
    tar czf "$out/sim_digit_report.tgz" -C "$TNF_DATA/reports" sim_digit
    ;;
  transfer)  # OmniTact: T-N, T-N+, FS
    for v in tn tn_plus fs; do
      tnf pipeline experiment=sim_omnitact_transfer transfer=$v device=cuda trainer=gpu progress=false
    done 2>&1 | tee "$out/transfer.log"
    tar czf "$out/sim_omnitact_transfer_report.tgz" -C "$TNF_DATA/reports" sim_omnitact_transfer
    ;;
  *) echo "unknown phase $1" >&2; exit 2 ;;
esac
