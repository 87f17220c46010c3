#!/usr/bin/env bash
# sim_digit_force (docs/force.md) on one machine of GPUS GPUs, one phase per call so that each fits a 10-minute job.
# Usage: bash experiments/force_runs.sh PHASE   (PHASE: data | models | decide | at-3n | report)
#   data    sim_digit's data in PAPER_DATA (experiments/paper_runs.sh digit-data), then the force store FORCE_DATA with
#           sim_digit's captures and scenes linked in, and its own touches and pairs
#   models  side by side, one process each, dealt round-robin over the GPUs: tn_cgan_force with force=plane
#           (STAGES, default train, generate, evaluate), force=film (train only: the decision needs its validation
#           SSIM), and sim_digit's fixed-force T-N (STAGES) for each of SEEDS. KINDS picks among plane, tn and film
#           (default all three). A run stopped by the job's limit resumes when the phase runs again.
#   decide  the rule of docs/force.md on seed 0's validation split: plane unless film's SSIM is 0.001 higher
#   at-3n   the chosen force models evaluated on sim_digit's own pairs (3 N), beside sim_digit's T-N
#   report  rebuild both reports and copy them to $OUT
# A CPU dry run at tiny scale: DEVICE=cpu TRAINER=cpu FIT_WORKERS=2 EXTRA="debug=tiny object_names=[...]" ...
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
paper=${PAPER_DATA:-/tmp/tnf-paper}
force=${FORCE_DATA:-/tmp/tnf-force}
export OUT=${OUT:-$force/out} PYTHONUNBUFFERED=1 OMP_NUM_THREADS=${OMP_NUM_THREADS:-2}
mkdir -p "$OUT"
seeds=${SEEDS:-0 1 2}
stages=${STAGES:-[train,generate,evaluate]}
gpus=${GPUS:-1}
extra=(${EXTRA:-})
dev=(device=${DEVICE:-cuda} trainer=${TRAINER:-gpu} progress=false "${extra[@]}")
tnf() { python -m tnf.cli "$@"; }
timed() {  # timed NAME CMD...: run, log to $OUT/NAME.log, append the wall time to $OUT/stage_times.txt
  local name=$1 t0=$SECONDS; shift
  "$@" >"$OUT/$name.log" 2>&1 || { tail -40 "$OUT/$name.log"; echo "FAILED: $name" | tee -a "$OUT/stage_times.txt"; return 1; }
  echo "$name: $((SECONDS - t0)) s" | tee -a "$OUT/stage_times.txt"
}
chosen() {  # the force input that decide wrote (plane until it has run)
  cat "$force/force_input.txt" 2>/dev/null || echo plane
}
case "${1:-}" in
  data)
    TNF_DATA=$paper bash "$here/paper_runs.sh" digit-scenes
    mkdir -p "$force"
    ln -sfn "$paper/capture" "$force/capture"
    ln -sfn "$paper/scenes" "$force/scenes"
    # sim_digit's touches and pairs (for fixed-force T-N and at-3n) beside the force store's, on two GPUs when there are.
    ( if ((gpus > 1)); then export CUDA_VISIBLE_DEVICES=0; fi
      TNF_DATA=$paper OUT=$OUT/digit bash "$here/paper_runs.sh" digit-pairs ) & p1=$!
    ( if ((gpus > 1)); then export CUDA_VISIBLE_DEVICES=1; fi
      TNF_DATA=$force OUT=$OUT/force EXPERIMENT=sim_digit_force bash "$here/paper_runs.sh" digit-pairs ) & p2=$!
    rc=0; wait $p1 || rc=1; wait $p2 || rc=1
    exit $rc
    ;;
  models)
    t0=$SECONDS
    jobs=()
    for k in ${KINDS:-plane tn film}; do for s in $seeds; do jobs+=("$k $s"); done; done
    run_one() {  # run_one KIND SEED
      case $1 in
        plane) TNF_DATA=$force tnf pipeline experiment=sim_digit_force "${dev[@]}" seed=$2 generator.force=plane \
          train.run_name=tn_cgan_force-digit-force-seed$2 "pipeline.stages=$stages" ;;
        film) TNF_DATA=$force tnf train experiment=sim_digit_force "${dev[@]}" seed=$2 generator.force=film \
          train.run_name=tn_cgan_film-digit-force-seed$2 ;;
        tn) TNF_DATA=$paper tnf pipeline experiment=sim_digit "${dev[@]}" seed=$2 generator=tn_cgan \
          "pipeline.stages=$stages" ;;
      esac
    }
    pids=() i=0
    for j in "${jobs[@]}"; do
      w=($j)
      ( if ((gpus > 1)); then export CUDA_VISIBLE_DEVICES=$((i % gpus)); fi
        timed "model-${w[0]}-seed${w[1]}" run_one "${w[0]}" "${w[1]}" ) & pids+=($!)
      i=$((i + 1))
    done
    rc=0; for p in "${pids[@]}"; do wait "$p" || rc=1; done
    echo "models: $((SECONDS - t0)) s" | tee -a "$OUT/stage_times.txt"
    exit $rc
    ;;
  decide)
    python - "$force/models" <<'PY' | tee "$OUT/decision.txt"
import csv, sys
from pathlib import Path
models = Path(sys.argv[1])
def at_best(run):
    rows = [r for r in csv.DictReader(open(models / run / "metrics.csv")) if r.get("val_l1")]
    best = min(rows, key=lambda r: float(r["val_l1"]))
    return int(float(best["epoch"])), float(best["val_ssim"])
(ep_p, plane), (ep_f, film) = at_best("tn_cgan_force-digit-force-seed0"), at_best("tn_cgan_film-digit-force-seed0")
print(f"plane: validation SSIM {plane:.4f} at its lowest validation L1 (epoch {ep_p})")
print(f"film:  validation SSIM {film:.4f} at its lowest validation L1 (epoch {ep_f})")
pick = "film" if film >= plane + 0.001 else "plane"
print(f"film - plane = {film - plane:+.4f}; the rule (film only if at least +0.001) keeps: {pick}")
(models.parent / "force_input.txt").write_text(pick + "\n")
PY
    ;;
  at-3n)
    # With film chosen, its three seeds need generate and evaluate first (plane's evaluated runs move aside).
    pick=$(chosen)
    pids=() i=0
    for s in $seeds; do
      run=tn_cgan_force-digit-force-seed$s
      [[ $pick == film ]] && run=tn_cgan_film-digit-force-seed$s
      ( if ((gpus > 1)); then export CUDA_VISIBLE_DEVICES=$((i % gpus)); fi
        TNF_DATA=$force timed "at-3n-seed$s" tnf evaluate experiment=sim_digit_force "${dev[@]}" seed=$s generator.force=$pick \
          evaluate.model=$run evaluate.dataset="$paper/pairs/digit-hashgrid" evaluate.name=sim_digit_force_at_3N \
          evaluate.classify.enabled=false ) & pids+=($!)
      i=$((i + 1))
    done
    rc=0; for p in "${pids[@]}"; do wait "$p" || rc=1; done
    exit $rc
    ;;
  report)
    TNF_DATA=$force tnf evaluate experiment=sim_digit_force "${dev[@]}" 2>&1 | tail -60 >"$OUT/report_force.log"
    TNF_DATA=$paper tnf evaluate experiment=sim_digit "${dev[@]}" 2>&1 | tail -60 >"$OUT/report_digit.log"
    mkdir -p "$OUT/reports"
    cp -r "$force/reports/." "$OUT/reports/" 2>/dev/null || true
    cp -r "$paper/reports/." "$OUT/reports/" 2>/dev/null || true
    for run in "$force"/models/* "$paper"/models/*; do
      [[ -f $run/metrics.csv ]] && mkdir -p "$OUT/metrics" && cp "$run/metrics.csv" "$OUT/metrics/$(basename "$run").csv"
    done
    ;;
  *) echo "usage: force_runs.sh PHASE; phases: data models decide report (got '${1:-}')" >&2; exit 2 ;;
esac
