#!/bin/bash
# Print the job list of the hard suite at the GPU settings, loop and no loop, one fit per line, for
# lab/device/queue.sh (the same code for both variants, so the loop's change needs no earlier rows):
#
#   bash lab/device/suite_jobs.sh "0 1" [LABEL [--set KEY=VALUE ...]] > jobs.txt
#
# SEEDS: a quoted list. LABEL (default "s"; required before --set) prefixes every run folder and
# held-out file under /root/stage; with --set the loop's fits carry the setting (no loop's do not: it has
# no mesh terms to change), so collect a candidate by its label (lab/device/collect.py --match
# LABEL_). Values must not contain spaces. The ten-view scenes come
# first (the slowest to settle: two fits each are worth more there), then the six dense objects; with the
# held-out scenes of lab/heldout.py at ten views of 512 px when HELDOUT=1 is set. SCENES (a quoted list)
# fits only those suite scenes (SCENES="mug_sparse" bash ... "4 5 6" c: more seeds of the ten-view cup; SCENES=""
# none, so HELDOUT=1 SCENES="" writes the held-out scenes alone). VARIANTS (a quoted list of lab/hard.py's
# variants, default "default no_loop") fits those beside each other: with
# VARIANTS="default no_loop no_geo_density no_mesh_terms" the loop is taken apart (--set applies to every variant
# but no_loop). PAIRED=1 writes one line per scene and seed that fits the warm-up once and every variant from
# it (hard.py --paired: the variants then differ only by what they change, not by the device's run-to-run
# spread, which on the ten-view cup is most of a fit's error: hard.md gpu_cup_seeds); its --set applies to
# every variant, and its fits run one after another (a ten-view line takes about 3,000 + 2 x 1,000 iterations).
# SPLIT=1 pairs the variants too, but runs them side by side: one line per scene and seed fits the warm-up
# (hard.py --warmup-only, then touches /root/stage/LABEL_warm_SCENE_SEED.done), and one line per variant waits
# for that file and branches from the warm-up (--set runtime.start_from=...); its --set applies to every variant.
# BY_VARIANT=1 orders those branch lines by variant (every scene's first variant, then every scene's second, ...), so a
# lease that ends before the queue does still leaves whole pairs when the first two variants are the pair (the
# held-out scenes' branch lines too, after the suite's).
# queue.sh runs the waiting lines after all others and gives every line its own truth cache, so the output of
# several calls may be concatenated; give it a PARALLEL of more than the number of warm-ups.
# With HELDOUT=1 too, the held-out scenes are split the same way (lab/heldout.py --warmup-only, then one
# line per variant from it), after the suite's lines. VARIANTS="default no_loop coevo1k coevo1k_no_loop" measures
# the loop at the GPU settings' co-evolution and at half it, all four from one warm-up per scene and seed.
set -euo pipefail
seeds=${1:-"0 1"}; label=${2:-s}
case "$label" in -*) echo "suite_jobs.sh: LABEL must come before --set, got '$label'" >&2; exit 2;; esac
shift $(( $# >= 2 ? 2 : $# )); sets="$*"
hard="python3 lab/hard.py --gpu --device cuda:0 --run-dir /root/stage"  # every suite line's start
n=0
branches=(); branch_variants=()  # SPLIT=1: the variants' lines, after every warm-up's, and each line's variant
emit_branches() {  # print the collected branch lines (by variant with BY_VARIANT=1) and forget them
  local variant i
  if [ "${BY_VARIANT:-0}" = 1 ]; then  # every scene's first variant, then every scene's second, ...
    for variant in ${VARIANTS:-default no_loop}; do
      for i in "${!branches[@]}"; do [ "${branch_variants[$i]}" = "$variant" ] && echo "${branches[$i]}"; done
    done
  else
    for i in "${!branches[@]}"; do echo "${branches[$i]}"; done
  fi
  branches=(); branch_variants=()
}
for scene in ${SCENES-mug_sparse chair_sparse torus_sparse torus chair chair_box bowl blob_flat mug}; do
  for seed in $seeds; do
    if [ "${SPLIT:-0}" = 1 ]; then
      w=/root/stage/${label}_warm_${scene}_${seed}
      echo "$hard --mesh-cache /root/stage/hc$n --label ${label}_warm_${scene}_${seed} --scenes $scene --variants default --seeds $seed --warmup-only $sets; touch $w.done"
      n=$((n + 1))
      for variant in ${VARIANTS:-default no_loop}; do
        branches+=("while [ ! -f $w.done ]; do sleep 10; done; $hard --mesh-cache /root/stage/hc$n --label ${label}_${variant}_${scene}_${seed} --scenes $scene --variants $variant --seeds $seed --set runtime.start_from=$w/seed$seed/${scene}_warmup $sets")
        branch_variants+=("$variant")
        n=$((n + 1))
      done
      continue
    fi
    if [ "${PAIRED:-0}" = 1 ]; then
      echo "$hard --mesh-cache /root/stage/hc$n --label ${label}_paired_${scene}_${seed} --scenes $scene --variants ${VARIANTS:-default no_loop} --seeds $seed --paired $sets"
      n=$((n + 1))
      continue
    fi
    for variant in ${VARIANTS:-default no_loop}; do
      extra=""; [ "$variant" != no_loop ] && extra="$sets"
      echo "$hard --mesh-cache /root/stage/hc$n --label ${label}_${variant}_${scene}_${seed} --scenes $scene --variants $variant --seeds $seed $extra"
      n=$((n + 1))
    done
  done
done
emit_branches
if [ "${HELDOUT:-0}" = 1 ]; then
  held="python3 lab/heldout.py --views 10 --resolution 512 --device cuda:0"
  for scene in vase pretzel table stool shelf; do
    for seed in $seeds; do
      if [ "${SPLIT:-0}" = 1 ]; then  # the warm-up, then every variant from it, as the suite's SPLIT lines
        w=/root/stage/hw_${label}_${scene}_${seed}.done
        echo "$held --scene $scene $seed default $w --tag $label --warmup-only $sets; touch $w"
        for variant in ${VARIANTS:-default no_loop}; do
          branches+=("while [ ! -f $w ]; do sleep 10; done; $held --scene $scene $seed $variant /root/stage/h_${label}_${scene}_${variant}_${seed}.json --tag $label --set runtime.start_from=runs/abl/${scene}_s${seed}_v10_r512_${label}_warmup $sets")
          branch_variants+=("$variant")
        done
        continue
      fi
      for mode in default noloop; do
        extra=""; [ "$mode" = default ] && extra="$sets"
        echo "python3 lab/heldout.py --scene $scene $seed $mode /root/stage/h_${label}_${scene}_${mode}_${seed}.json --views 10 --resolution 512 --device cuda:0 $extra"
      done
    done
  done
fi
emit_branches  # the held-out scenes' branch lines, after their warm-ups
