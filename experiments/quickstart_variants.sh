#!/usr/bin/env bash
# Quick-start variants on several seeds, scored on the validation split only (never a test split).
# Usage: bash experiments/quickstart_variants.sh   (env: SEEDS="0 1 2", VARIANTS="base sensor residual more",
#        DEVICE=cuda TRAINER=gpu, ROOT=/tmp/qs, OUT=folder for the logs and the table, CLASSIFY=1)
# Per seed, capture and fit-scene run once; each variant then copies the fitted scenes and runs touch, pair and
# train on its own store, all variants and seeds in parallel. Each run is scored with experiments/val_metrics.py
# (mirror-averaged, as the quick start generates) beside BG; the table goes to $OUT/variants.txt. CLASSIFY=1 also
# generates and runs the classification task with the validation touches as its test set (evaluate.name=val,
# no image metrics), and adds each run's Sim and Sim + T-N accuracy to the table. With NOVEL=1 that evaluation
# also scores the novel_object split: give the variants validation objects of their own to hold out (never the
# quick start's test object), and SCENE_OBJECTS=a,b,... every object the variants use, fitted once per seed.
# CONE=1 tests the classifier on the novel_view split instead, and scores that split's images too: give the
# variants a held-out cone of their own (touch.novel_view_axis, never the quick start's), as the test's classifier
# is scored on touches from a cone that no Sim touch comes from.
set -euo pipefail
export PYTHONUNBUFFERED=1 OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
seeds=(${SEEDS:-0 1 2})
variants=(${VARIANTS:-base sensor residual more})
root=${ROOT:-/tmp/qs}
out=${OUT:-$root/out}
dev=(device=${DEVICE:-cuda} trainer=${TRAINER:-gpu} progress=false ${EXTRA:-})
[[ ${TRAINER:-gpu} == gpu ]] && dev+=(trainer.precision=32-true)
mkdir -p "$out"
tnf() { python -m tnf.cli "$@"; }
overrides() {  # the settings of each variant, on top of experiment=quickstart
  case $1 in
    base) ;;
    sensor) echo pair.crop_extent=sensor ;;
    residual) echo pair.crop_extent=sensor generator=tn_cgan ;;
    more) echo pair.crop_extent=sensor generator=tn_cgan touch.n_touches=200 train.epochs=15 train.decay_epochs=8 ;;
    cls) echo "$(overrides more) touch.n_val=20 touch.n_novel_view=30 generate.n_poses=40" \
      evaluate.classifier.real_fraction=0.5 evaluate.classifier.steps=300 ;;
    gan) echo "$(overrides more) generator.lambda_gan=0.1" ;;
    gancls) echo "$(overrides cls) generator.lambda_gan=0.1" ;;
    gan1cls) echo "$(overrides cls) generator.lambda_gan=1.0" ;;
    # round 4: bottle and gear held out as validation novel objects (drawn at random), banana left out
    r3v) echo "$(overrides gan1cls) object_names=[box,can,mug,bottle,gear] pair.novel_objects=[bottle,gear]" ;;
    widev) echo "$(overrides gan1cls) object_names=[box,can,mug,pepper,spray_can,bottle,gear]" \
      pair.novel_objects=[bottle,gear] touch.n_touches=120 ;;
    # round 5: the classification rows as the mean of 5 classifiers each
    r3v5) echo "$(overrides r3v) evaluate.classifier.restarts=5" ;;
    widev5) echo "$(overrides widev) evaluate.classifier.restarts=5" ;;
    # round 6: three times the generated touches per object, and a larger share of ground truth per batch
    r3v5g) echo "$(overrides r3v5) generate.n_poses=120" ;;
    widev5g) echo "$(overrides widev5) generate.n_poses=120" ;;
    widev5g75) echo "$(overrides widev5g) evaluate.classifier.real_fraction=0.75" ;;
    # round 7: the least-squares adversarial loss, against round 6's collapses to the background image
    r3v5gls) echo "$(overrides r3v5g) generator.gan_mode=lsgan" ;;
    widev5gls) echo "$(overrides widev5g) generator.gan_mode=lsgan" ;;
    widev5g75ls) echo "$(overrides widev5g75) generator.gan_mode=lsgan" ;;
    # round 8: a weaker discriminator (half the width, one layer fewer), against the saturation behind the collapses
    r3v5d8) echo "$(overrides r3v5) generator.ndf=8" ;;
    r3v5dl2) echo "$(overrides r3v5) generator.d_layers=2" ;;
    r3v5d8l2) echo "$(overrides r3v5) generator.ndf=8 generator.d_layers=2" ;;
    # round 9: half the ground-truth touches per object in the classifier's Sim set (5, was 10)
    r3v5s5) echo "$(overrides r3v5) evaluate.classify.sim_per_object=5" ;;
    r3v5d8s5) echo "$(overrides r3v5d8) evaluate.classify.sim_per_object=5" ;;
    # round 10: four validation novel objects (bottle, gear and two drawn at random: wrench, bolt)
    r3v5s5w) echo "$(overrides r3v5s5) pair.novel_objects=[bottle,gear,wrench,bolt]" \
      object_names=[box,can,mug,bottle,gear,wrench,bolt] ;;
    r3v5d8s5w) echo "$(overrides r3v5d8s5) pair.novel_objects=[bottle,gear,wrench,bolt]" \
      object_names=[box,can,mug,bottle,gear,wrench,bolt] ;;
    r3v5d8l2s5w) echo "$(overrides r3v5d8s5w) generator.d_layers=2" ;;
    r3v5d4s5w) echo "$(overrides r3v5d8s5w) generator.ndf=4" ;;
    # round 11: the simulator's image of each depth crop (pair.prior) as a fourth input, the residual added to the
    # background (p) or to the prior (pr)
    r3v5d8s5wp) echo "$(overrides r3v5d8s5w) pair.prior=true generator.inputs=[rgb,depth_and_slope,background,prior]" \
      generator.skips=[background,depth_and_slope,prior] ;;
    r3v5d8s5wpr) echo "$(overrides r3v5d8s5wp) generator.residual_on=prior" ;;
    r3v5s5wp) echo "$(overrides r3v5d8s5wp) generator.ndf=16" ;;
    # round 12 (fresh seeds, each restart with its own draw of the Sim touches): round 11's, without the T-N only row
    r3v5d8s5wn) echo "$(overrides r3v5d8s5w) evaluate.classify.generated_only=false" ;;
    r3v5d8s5wpn) echo "$(overrides r3v5d8s5wp) evaluate.classify.generated_only=false" ;;
    r3v5s5wpn) echo "$(overrides r3v5s5wp) evaluate.classify.generated_only=false" ;;
    # round 13 (fresh seeds): round 10's discriminator of width 16 without the T-N only row, and the crops rendered
    # at 32 px (were 48) for time, with a discriminator of width 16 or 8
    r3v5s5wn) echo "$(overrides r3v5s5w) evaluate.classify.generated_only=false" ;;
    r3v5s5w32n) echo "$(overrides r3v5s5wn) pair.render_px=32" ;;
    r3v5d8s5w32n) echo "$(overrides r3v5d8s5wn) pair.render_px=32" ;;
    # after round 13, a diagnosis (no pick): each novel object's margin over BG, on eight validation novel objects
    # (round 10's four and four drawn with random.Random(14): brick, polish_tin, shampoo, sponge), without and with
    # the prior input
    r3v5s5w32n8) echo "$(overrides r3v5s5w32n) pair.novel_objects=[bottle,gear,wrench,bolt,brick,polish_tin,shampoo,sponge]" \
      object_names=[box,can,mug,bottle,gear,wrench,bolt,brick,polish_tin,shampoo,sponge] ;;
    r3v5s5w32pn8) echo "$(overrides r3v5s5w32n8) pair.prior=true generator.inputs=[rgb,depth_and_slope,background,prior]" \
      generator.skips=[background,depth_and_slope,prior] ;;
    r3v5s5w32n8g0) echo "$(overrides r3v5s5w32n8) generator.lambda_gan=0" ;;
    # round 14: three rounded validation novel objects, like the test's three (6 classes, as the test), with the
    # adversarial term at its weight of 1 (round 13's pick) and at 0.3
    r3v5s5w32n3) echo "$(overrides r3v5s5w32n) pair.novel_objects=[bottle,polish_tin,shampoo]" \
      object_names=[box,can,mug,bottle,polish_tin,shampoo] ;;
    r3v5s5w32n3g3) echo "$(overrides r3v5s5w32n3) generator.lambda_gan=0.3" ;;
    # round 15 (with CONE=1): round 14's pick, its held-out cone of start directions about +y (the test's is about
    # +x), with 40 (c40) or 80 (c80) generated touches per object
    r3v5s5w32n3g3c40) echo "$(overrides r3v5s5w32n3g3) touch.novel_view_axis=[0.0,1.0,0.0]" ;;
    r3v5s5w32n3g3c80) echo "$(overrides r3v5s5w32n3g3c40) generate.n_poses=80" ;;
    # after round 15's test, a diagnosis (no pick): its pick with the test's novel objects (banana, lemon,
    # paper_cup) on the +y cone (tobj), and with the validation objects on the test's +x cone (xcone)
    tobj) echo "$(overrides r3v5s5w32n3g3c80) pair.novel_objects=[banana,lemon,paper_cup]" \
      object_names=[box,can,mug,banana,lemon,paper_cup] ;;
    xcone) echo "$(overrides r3v5s5w32n3g3c80) touch.novel_view_axis=[1.0,0.0,0.0]" ;;
    # round 16 (with CONE=1): round 14's pick on the +y cone with three rounded validation novel objects with fine
    # relief, like the test's (golf_ball, jar, vase), and half (0.5) or three quarters (f75) of each Sim + T-N batch
    # from the ground truth, the latter also with the adversarial weight 1 (g1f75)
    r16) echo "$(overrides r3v5s5w32n3g3c40) pair.novel_objects=[golf_ball,jar,vase]" \
      object_names=[box,can,mug,golf_ball,jar,vase] ;;
    r16f75) echo "$(overrides r16) evaluate.classifier.real_fraction=0.75" ;;
    r16g1f75) echo "$(overrides r16f75) generator.lambda_gan=1.0" ;;
    # after round 16, a diagnosis (no pick): a training object with fine relief (bottle: a ribbed waist, a knurled
    # cap) in place of the mug
    r16b) echo "$(overrides r16)" object_names=[box,can,bottle,golf_ball,jar,vase] ;;
    # and the adversarial term's gradient kept within 4 px of each press (generator.gan_press_margin=4)
    r16pm) echo "$(overrides r16) generator.gan_press_margin=4" ;;
    # and without the adversarial term
    r16g0) echo "$(overrides r16) generator.lambda_gan=0" ;;
    # round 17 (with EXTRA="fit.distortion_weight=W", each weight its own store): r16 on scenes fitted with the
    # distortion loss; round 18: r17d (the weight 0.1, run with EXTRA="fit.distortion_weight=0.1"), with the
    # adversarial gradient kept within 4 px of each press (pm), the adversarial weight 0.1 (g01), or both
    r17d) echo "$(overrides r16)" ;;
    r18pm) echo "$(overrides r17d) generator.gan_press_margin=4" ;;
    r18g01) echo "$(overrides r17d) generator.lambda_gan=0.1" ;;
    r18pmg01) echo "$(overrides r18pm) generator.lambda_gan=0.1" ;;
    # round 19 (with CONE=1): the committed quick start with ball as its validation novel object, its scenes fitted
    # without (q19, EXTRA="fit.distortion_weight=0.0") or with the distortion loss (q19d, EXTRA="fit.distortion_weight=0.1")
    q19) echo object_names=[box,can,mug,ball] pair.novel_objects=[ball] touch.novel_view_axis=[0.0,1.0,0.0] ;;
    q19d) echo "$(overrides q19)" ;;
    # round 20 (with EXTRA="fit.distortion_weight=0.1"): q19d with round 18's generator settings (32 px crops, the
    # adversarial weight 0.3 kept within 4 px of each press)
    q20) echo "$(overrides q19d) pair.render_px=32 generator.lambda_gan=0.3 generator.gan_press_margin=4" ;;
    # round 21 (with CONE=1 and EXTRA="fit.distortion_weight=0.1"): round 18's pick with every generated touch drawn
    # inside the held-out cone (the views no Sim touch comes from)
    r21) echo "$(overrides r18pm) generate.directions=novel_view" ;;
    *) echo "unknown variant $1" >&2; return 1 ;;
  esac
}
splits=${NOVEL:+novel_object}${CONE:+${NOVEL:+,}novel_view}
cls_split=val
[[ -z ${CONE:-} ]] || cls_split=novel_view
t0=$SECONDS
for s in "${seeds[@]}"; do
  (tnf pipeline "${dev[@]}" seed=$s data_root=$root/s$s/scenes "pipeline.stages=[capture,fit-scene]" \
    ${SCENE_OBJECTS:+object_names=[$SCENE_OBJECTS]} \
    >"$out/scenes-s$s.log" 2>&1 || { tail -20 "$out/scenes-s$s.log"; exit 1; }) &
done
wait
echo "scenes: $((SECONDS - t0)) s"
for s in "${seeds[@]}"; do
  for v in "${variants[@]}"; do
    (
      r=$root/s$s/$v
      mkdir -p "$r" && cp -r "$root/s$s/scenes/." "$r/"
      read -ra o <<<"$(overrides "$v")"
      tnf pipeline "${dev[@]}" seed=$s data_root=$r "${o[@]}" train.run_name=$v \
        "pipeline.stages=[touch,pair,train]" >"$out/$v-s$s.log" 2>&1 || { tail -30 "$out/$v-s$s.log"; exit 1; }
      ds=$(basename "$(ls -d "$r"/pairs/*/ | head -1)")
      python experiments/val_metrics.py --data-root "$r" --dataset "$ds" --split val --mirror-average \
        --device "${DEVICE:-cuda}" "$v" >"$out/val-$v-s$s.txt" 2>&1
      if [[ ${CLASSIFY:-0} == 1 ]]; then
        tnf pipeline "${dev[@]}" seed=$s data_root=$r "${o[@]}" train.run_name=$v "pipeline.stages=[generate,evaluate]" \
          evaluate.name=val "evaluate.splits=[${splits}]" "evaluate.classify.test_splits=[$cls_split]" \
          >"$out/cls-$v-s$s.log" 2>&1 ||
          { tail -30 "$out/cls-$v-s$s.log"; exit 1; }
        grep -E "^(Sim|Sim \+ T-N)," "$r/reports/val/table1b_accuracy.csv" >>"$out/val-$v-s$s.txt"
        [[ -z $splits ]] || grep -E "^novel_(object|view),(T-N|BG)," "$r/reports/val/table1a_image.csv" >>"$out/val-$v-s$s.txt"
      fi
    ) &
  done
done
wait
echo "variants: $((SECONDS - t0)) s"
for f in "$out"/val-*.txt; do echo "== $(basename "$f" .txt)"; tail -10 "$f"; done | tee "$out/variants.txt"
