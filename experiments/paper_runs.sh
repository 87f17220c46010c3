#!/usr/bin/env bash
# The paper-scale runs of results/paper/ on one GPU, one phase per call so that each fits a 10-minute job.
# Usage: bash experiments/paper_runs.sh PHASE   (PHASE: bench | digit-data | digit-models | transfer | report)
#   digit-data    digit-scenes with touch beside it, then pair (OVERLAP=0: digit-scenes, digit-pairs)  (sim_digit)
#   digit-scenes  capture, fit-scene (one process, its 27 scenes in one batched fit, under cProfile with
#                 FIT_PROFILE=1; FIT_WORKERS=N>1: a sweep of N jobs over object shards through Hydra's joblib
#                 launcher, spread over the visible GPUs by tnf); every scene's figures to scenes.txt/.csv
#   digit-pairs   touch, pair (with PROFILE=1, here and in digit-data, pair runs under cProfile: the top functions
#                 go to $OUT/pair_profile.txt)
#   digit-models  train + generate + evaluate for each of GENERATORS (default tn_cgan lee cyclegan) and SEEDS, one
#                 process each (on one H100, one seed's three generators take 664-712 s, three tn_cgan seeds of 45
#                 epochs 610-760 s: a 10-minute job stops them, and the next resumes them)
#   transfer      OmniTact touches and pairs, then T-N, T-N+ and FS fine-tuned in parallel for each of SEEDS
#   train-scaling tn_cgan on sim_digit's pairs (after digit-data) for SCALING_EPOCHS epochs on 1 GPU, then with
#                 trainer=ddp on 2, 4, ... up to GPUS GPUs, one run at a time; wall times and each run's figures
#   report        rebuild both reports from every run present and copy them to $OUT
# Artifacts go to $TNF_DATA (default /tmp/tnf-paper); logs, stage times and reports go to $OUT when it is set.
# The end-to-end time of sim_digit for one seed is the sum of the digit-data and digit-models stage times.
set -euo pipefail
export TNF_DATA=${TNF_DATA:-/tmp/tnf-paper} PYTHONUNBUFFERED=1
# Several tnf processes share the machine's cores: torch's default of one thread per core in each of them
# oversubscribes the CPU (six fit workers ran 3x slower per step than one).
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-2}
out=${OUT:-$TNF_DATA/out}
seeds=${SEEDS:-0}
fit_workers=${FIT_WORKERS:-1}
# On a machine of several GPUs, GPUS=N deals the parallel processes of digit-models and transfer (one per generator
# and seed) round-robin over the first N (CUDA_VISIBLE_DEVICES); capture, touch and pair run on the GPU that
# CUDA_VISIBLE_DEVICES names; the fit sweep's jobs spread over every visible GPU by themselves (docs/cluster.md).
gpus=${GPUS:-1}
on_gpu() {  # on_gpu I: in a subshell, pin it to GPU I mod N when GPUS=N > 1
  if ((gpus > 1)); then export CUDA_VISIBLE_DEVICES=$(($1 % gpus)); fi
}
# More overrides for every command. A dry run on a CPU:
# DEVICE=cpu TRAINER=cpu FIT_WORKERS=2 EXTRA="debug=tiny object_names=[ball,box,can,mug] ..."
extra=(${EXTRA:-})
mkdir -p "$out"
tnf() { python -m tnf.cli "$@"; }
dev=(device=${DEVICE:-cuda} trainer=${TRAINER:-gpu} progress=false "${extra[@]}")
# EXPERIMENT runs the digit-* phases on another experiment of sim_digit's objects (sim_gelsight_mini_gpu;
# sim_digit_force in its own TNF_DATA, with GENERATORS=tn_cgan_force: docs/force.md gives its phases).
experiment=${EXPERIMENT:-sim_digit}
digit=(experiment=$experiment "${dev[@]}")
timed() {  # timed NAME CMD...: run, log to $out/NAME.log, append the wall time to $out/stage_times.txt
  local name=$1 t0=$SECONDS; shift
  "$@" >"$out/$name.log" 2>&1 || { tail -40 "$out/$name.log"; echo "FAILED: $name" | tee -a "$out/stage_times.txt"; return 1; }
  echo "$name: $((SECONDS - t0)) s" | tee -a "$out/stage_times.txt"
}
pair_stage() {  # tnf pair, timed; with PROFILE=1 under cProfile (the top functions to $out/pair_profile.txt)
  if [[ ${PROFILE:-0} == 1 ]]; then
    timed pair python -m cProfile -o "$out/pair.prof" -m tnf.cli pair "${digit[@]}" || return 1
    python -c "import pstats; pstats.Stats('$out/pair.prof').sort_stats('tottime').print_stats(40)" >"$out/pair_profile.txt"
    rm -f "$out/pair.prof"
  else
    timed pair tnf pair "${digit[@]}"
  fi
}
case "${1:-}" in
  bench)
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv | tee "$out/hardware.txt"
    python -c "import torch, warp, lightning; print('torch', torch.__version__, 'warp', warp.__version__, 'lightning', lightning.__version__)" | tee -a "$out/hardware.txt"
    python bench/sim.py --device cuda --batch 512 2>&1 | tee "$out/bench_sim_cuda.txt"
    python bench/capture.py --device cuda 2>&1 | tee "$out/bench_capture_gpu.txt"
    python bench/scenes.py --device cuda --object box --steps 1500 --out /tmp/bench-scenes 2>&1 | tee "$out/bench_scenes_cuda.txt"
    python bench/loading.py --device cuda --workers 4 2>&1 | tee "$out/bench_loading_cuda.txt"
    ;;
  digit-data)
    # Touch needs no scene: it runs beside capture and the fits (OVERLAP=0: one stage after another).
    if [[ ${OVERLAP:-1} == 1 ]]; then
      t0=$SECONDS
      timed touch tnf touch "${digit[@]}" & touch_pid=$!
      rc=0; bash "$0" digit-scenes || rc=1
      wait $touch_pid || rc=1
      ((rc == 0)) && { pair_stage || rc=1; }
      echo "digit-data: $((SECONDS - t0)) s" | tee -a "$out/stage_times.txt"
      exit $rc
    else
      bash "$0" digit-scenes && bash "$0" digit-pairs
    fi
    ;;
  digit-scenes)
    t0=$SECONDS
    timed capture tnf capture "${digit[@]}"
    if ((fit_workers == 1)); then
      # One process (sim_digit's fit.batch_objects=27: all objects in one training loop); FIT_PROFILE=1 runs it
      # under cProfile, the top functions by cumulative time to $out/fit_profile.txt.
      if [[ ${FIT_PROFILE:-0} == 1 ]]; then
        timed fit python -m cProfile -o "$out/fit.prof" -m tnf.cli fit-scene "${digit[@]}"
        python -c "import pstats; pstats.Stats('$out/fit.prof').sort_stats('cumulative').print_stats(60)" >"$out/fit_profile.txt"
        rm -f "$out/fit.prof"
      else
        timed fit tnf fit-scene "${digit[@]}"
      fi
    else
      # One sweep over object shards, as a user would run it on several GPUs (each job batches its own shard).
      timed fit tnf fit-scene -m hydra/launcher=joblib hydra.launcher.n_jobs=$fit_workers shards=$fit_workers \
        "shard=range($fit_workers)" "${digit[@]}"
    fi
    echo "digit-scenes: $((SECONDS - t0)) s" | tee -a "$out/stage_times.txt"
    # The table of every scene (hashgrid, builtin: sim_digit's); a failure here leaves the fitted scenes usable.
    python experiments/scene_table.py "$TNF_DATA" --csv "$out/scenes.csv" >"$out/scenes.txt" 2>&1 && tail -2 "$out/scenes.txt" ||
      echo "scene table not written (see $out/scenes.txt)"
    ;;
  digit-pairs)
    t0=$SECONDS
    timed touch tnf touch "${digit[@]}"
    pair_stage
    echo "digit-pairs: $((SECONDS - t0)) s" | tee -a "$out/stage_times.txt"
    ;;
  digit-models)
    t0=$SECONDS
    jobs=() names=()
    # CycleGAN's two ResNet generators train at ~200 pairs/s on an H100 (tn_cgan: ~3,500; results/generators):
    # sim_digit's 45 epochs would take 45 minutes, so it gets CYCLEGAN_EPOCHS (default 3, as every committed
    # CycleGAN row; docs/decisions/paper_gap.md says so).
    # BASELINE_PATIENCE=P trains Lee and CycleGAN to a plateau instead: until P validations in a row raise
    # validation SSIM by no more than 0.0001, at a constant rate, at most BASELINE_MAX_EPOCHS (default 200). A call
    # cut short by its time limit resumes with the same command. These runs go to their own report
    # (<experiment>_plateau), beside the fixed-epoch rows; it draws every run's validation curve.
    ce=${CYCLEGAN_EPOCHS:-3}
    for s in $seeds; do for g in ${GENERATORS:-tn_cgan lee cyclegan}; do
      j="generator=$g seed=$s" name="model-$g-seed=$s"
      if [[ -n ${BASELINE_PATIENCE:-} && $g != tn_cgan ]]; then
        j+=" train.patience=$BASELINE_PATIENCE train.epochs=${BASELINE_MAX_EPOCHS:-200} train.decay_epochs=0"
        j+=" evaluate.name=${experiment}_plateau" name+="-plateau"
      else
        j+=" evaluate.name=$experiment"  # named: a dry run at debug=tiny would report to reports/tiny
        [[ $g != cyclegan ]] || j+=" train.epochs=$ce train.decay_epochs=$((ce / 2))"
      fi
      jobs+=("$j") names+=("$name")
    done; done
    run_one() { tnf pipeline "${digit[@]}" "pipeline.stages=[train,generate,evaluate]" $1; }
    pids=() i=0
    for j in "${jobs[@]}"; do
      ( on_gpu $i; timed "${names[$i]}" run_one "$j" ) & pids+=($!); i=$((i + 1))
    done
    rc=0; for p in "${pids[@]}"; do wait "$p" || rc=1; done
    echo "digit-models: $((SECONDS - t0)) s" | tee -a "$out/stage_times.txt"
    exit $rc
    ;;
  transfer)
    t0=$SECONDS
    omni=(experiment=sim_omnitact_transfer "${dev[@]}")
    timed omnitact-touch tnf touch "${omni[@]}"
    timed omnitact-pair tnf pair "${omni[@]}"
    run_one() { tnf pipeline "${omni[@]}" "pipeline.stages=[finetune,generate,evaluate]" $1; }
    pids=() i=0
    for s in $seeds; do for v in tn tn_plus fs; do
      ( on_gpu $i; timed "transfer-$v-seed$s" run_one "transfer=$v seed=$s" ) & pids+=($!); i=$((i + 1))
    done; done
    rc=0; for p in "${pids[@]}"; do wait "$p" || rc=1; done
    echo "transfer: $((SECONDS - t0)) s" | tee -a "$out/stage_times.txt"
    exit $rc
    ;;
  train-scaling)
    # Wall times include start-up (reading the pairs, starting DDP's processes); bf16 on every run, as trainer=gpu.
    # A dry run on a CPU: the dry run of digit-data above, then GPUS=2 DDP_ACCELERATOR=cpu DDP_PRECISION=32-true.
    ep=${SCALING_EPOCHS:-6}
    base=(experiment=sim_digit device=${DEVICE:-cuda} progress=false "${extra[@]}" seed=0 train.epochs=$ep
      train.decay_epochs=0)
    rc=0
    for ((n = 1; n <= gpus; n *= 2)); do
      tr=(trainer=${TRAINER:-gpu})
      ((n > 1)) && tr=(trainer=ddp trainer.accelerator=${DDP_ACCELERATOR:-gpu} trainer.devices=$n
        trainer.precision=${DDP_PRECISION:-bf16-mixed})
      rm -rf "$TNF_DATA/models/scaling_${n}gpu"  # this phase's own runs: each starts afresh
      timed "train-scaling-${n}gpu" tnf train "${base[@]}" "${tr[@]}" train.run_name=scaling_${n}gpu ||
        { rc=1; continue; }
      python - "$TNF_DATA/models/scaling_${n}gpu" <<'PY' | tee -a "$out/stage_times.txt"
import csv, json, sys
from pathlib import Path
run = Path(sys.argv[1])
m = json.loads((run / "manifest.json").read_text())
rows = [r for r in csv.DictReader(open(run / "metrics.csv")) if r.get("train/samples")]
print(f"  {m['world_size']} device(s): {m['epochs']} epochs of {float(rows[-1]['train/samples']):.0f} pairs, "
      f"{m['global_step']} steps, last val SSIM {m['last']['val_ssim']:.4f}, best val L1 {m['best_val_l1']:.4f}")
PY
    done
    exit $rc
    ;;
  report)
    # Jobs that ran in parallel each rebuilt the reports; rebuild each once more from every run present.
    if [[ -d $TNF_DATA/reports/$experiment/runs ]]; then
      tnf evaluate experiment=$experiment "${dev[@]}" 2>&1 | tee "$out/report_$experiment.log"
    fi
    if [[ -d $TNF_DATA/reports/${experiment}_plateau/runs ]]; then
      tnf evaluate experiment=$experiment evaluate.name=${experiment}_plateau "${dev[@]}" 2>&1 |
        tee "$out/report_${experiment}_plateau.log"
    fi
    tnf evaluate experiment=sim_omnitact_transfer "${dev[@]}" 2>&1 | tee "$out/report_transfer.log" || true
    tar czf "$out/reports.tgz" -C "$TNF_DATA/reports" .
    ;;
  *) echo "usage: paper_runs.sh PHASE; phases: bench digit-data digit-scenes digit-pairs digit-models transfer train-scaling report (got '${1:-}')" >&2; exit 2 ;;
esac
