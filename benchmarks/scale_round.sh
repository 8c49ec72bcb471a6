#!/usr/bin/env bash
# Issue 54's round in the background: the render and every run, each job started at most once (a lock per job, so
# rerunning this script starts only what is not running) and each resuming from its own files. Rerun it after a stop,
# a new session or a new machine (docs/training.md, "The scale set's round", gives each command and why).
# Jobs (default: all, in this order; logs in LOGS/JOB.log):
#   render        benchmarks/scale_render.sh: val, the 1x, 3x and 10x subsets, test, the rest
#   fusesr        FuseSR's curve: 1x, 3x, 10x from scratch (6,000 steps each), scored once the test split is whole
#   fusesr-10x    FuseSR's 10x run (train only, beside the curve, which waits for it), then its release by the val
#                 rule after the fine-tune's (each candidate faces what is shipped when its turn comes)
#   fusesr-l      FuseSR-l's curve, the same way
#   fusesr-l-10x  FuseSR-l's 10x run (train only), then its release by the val rule
#   finetune      the shipped FuseSR fine-tuned (3,000 steps) on the 10x subset once it is rendered (the 10x run's
#                 clips), then its release by the val rule
#   inputs        the inputs study: FuseSR-l's 1x run again with hr_material (HR roughness and metallic), all else
#                 as the curve's 1x run, and the 1x run at seed 1; scored on val side by side (val only)
#   end           the round's end, once both curves are scored and every release has run: the test split's scores
#                 of what shipped and every record docs/results.md reads (the sections and the verdict are written
#                 by hand; its last step marks RUNS/round-end.done)
# A release writes training/weights/ here: commit the weights with their JSON and model card (make generate).
# The render reads this checkout's code for every clip (each frame records its commit): run the render job from a
# checkout that does not change meanwhile (a `git worktree add --detach` at main's HEAD) and the others from this one.
# Usage: benchmarks/scale_round.sh [JOB...]
#   DATA (default datasets/scale), RUNS (default runs), LOGS (default RUNS/round-logs), W: the render's workers
#   (default 2); NICE (default 10): the trainings' niceness (on Linux that of their own autogroup, so that the render,
#   niceness 0, keeps its cores); DRY=1: print each job's commands in order and start nothing.
set -euo pipefail
SELF=$(cd "$(dirname "$0")" && pwd)/$(basename "$0")
cd "$(dirname "$SELF")/.."
DATA=${DATA:-datasets/scale}
RUNS=${RUNS:-runs}
LOGS=${LOGS:-$RUNS/round-logs}
NICE=${NICE:-10}
PY=${PY:-.venv/bin/python}
WAIT=${WAIT:-600}
SCALING=("$PY" benchmarks/data_scaling.py "$DATA" --runs "$RUNS/scaling" --steps 6000 --threads 1 --wait $((WAIT / 60)))
FT=$RUNS/finetune/fusesr
IN=$RUNS/inputs/fusesr-l_047clips_material
IN_SEED=$RUNS/inputs/fusesr-l_047clips_seed1
JOBS=(render fusesr fusesr-10x fusesr-l fusesr-l-10x finetune inputs end)

run() { echo "+ $*"; [ "${DRY:-0}" = 1 ] || "$@"; }
mark() { [ "${DRY:-0}" = 1 ] || touch "$1"; }
# until a python expression holds (each look every WAIT seconds); DRY: say so once
await() { echo "+ until $1"; [ "${DRY:-0}" = 1 ] && return; until "$PY" -c "import os, sys; sys.exit(not ($1))"; do
  sleep "$WAIT"; done; }
# the release of RUN for MODEL by the val rule on held-out-family val, the test split deferred to the round's end
# (once: RUN/released marks it done, whichever way the rule went; the log says which)
release() {
  local model=$1 run=$2
  [ -f "$run/released" ] && { echo "$run: released already"; return; }
  run "$PY" benchmarks/release_weights.py "$DATA" "$(dirname "$run")" --models "$model" --script '' \
      --run "$model=$run" --options "$model?residual_clamp=lr-guided" --defer-test
  mark "$run/released"
}

body_render() { run bash benchmarks/scale_render.sh "$DATA"; }
body_fusesr() {
  run "${SCALING[@]}" --multiples 1,3,10 -o docs/bench/scaling-families/fusesr --model fusesr \
      --score-options residual_clamp=lr-guided
  mark "$RUNS/scaling/fusesr.scored"
}
body_fusesr_l() {
  run "${SCALING[@]}" --multiples 1,3,10 -o docs/bench/scaling-families/fusesr-l --model fusesr-l \
      --score-options 'residual_clamp=lr-range;residual_clamp=lr-guided'
  mark "$RUNS/scaling/fusesr-l.scored"
}
body_fusesr_l_10x() {
  run "${SCALING[@]}" --multiples 10 -o docs/bench/scaling-families/fusesr-l --model fusesr-l --train-only
  release fusesr-l "$RUNS/scaling/fusesr-l_470clips"
}
body_fusesr_10x() {
  run "${SCALING[@]}" --multiples 10 -o docs/bench/scaling-families/fusesr --model fusesr --train-only
  await "__import__('os').path.exists('$FT/released')"
  release fusesr "$RUNS/scaling/fusesr_470clips"
}
# the fine-tune's recipe (docs/training.md): from the shipped weights, benchmarks/pretrain.toml at lr 1e-4, the bound
# lr-guided, the temporal loss at 0.5
body_finetune() {
  [ -f "$FT/released" ] && { echo "$FT: released already"; return; }
  local subset=$FT.subset.txt
  [ "${DRY:-0}" = 1 ] || mkdir -p "$FT"
  run "$PY" benchmarks/data_scaling.py "$DATA" -o - --multiples 1,3,10 --list-clips "$subset"
  # the subset's clip folders by the index's own path rule (build.split_clips), once every one is finished and valid
  local want="set(open('$subset').read().split())" build="__import__('gbuffer_export.dataset.build', fromlist=['x'])"
  local paths="[str(p) for p in $build.split_clips('$DATA', 'train') if p.name in $want]"
  await "len($paths) == len($want)"
  local data=("@$subset")
  [ "${DRY:-0}" = 1 ] || mapfile -t data < <("$PY" -c "print('\\n'.join($paths))")
  local cmd=(.venv/bin/blendsr train --model fusesr --data "${data[@]}" -o "$FT"
             --config benchmarks/pretrain.toml --max-steps 3000 --set run.threads=1
             --set 'run.init_from="pretrained:fusesr"' --set optim.lr=1e-4
             --set 'model.fusesr.residual_clamp="lr-guided"' --set model.scale=4 --set loss.temporal_weight=0.5)
  [ "${DRY:-0}" = 1 ] || { printf '%q ' "${cmd[@]}" > "$FT/command.txt"; }
  if [ -f "$FT/checkpoints/last.pt" ]; then run "${cmd[@]}" --resume; else run "${cmd[@]}"; fi
  release fusesr "$FT"
}

# the inputs study (docs/training.md, "The inputs study"): the curve's 1x FuseSR-l run, config and all, with the HR
# material inputs added, and the 1x run again at another seed (the noise floor); the three scored on val side by
# side (the test split is not read) once all have their 6,000 steps, then grouped by family (held-out assets)
body_inputs() {
  local base=$RUNS/scaling/fusesr-l_047clips done="lambda r: __import__('json').load(open(r + '/summary.json'))"
  await "__import__('os').path.exists('$base/config.toml')"
  local run sets
  for run in "$IN" "$IN_SEED"; do
    sets=(--set model.fusesr-l.hr_material=true)
    [ "$run" = "$IN_SEED" ] && sets=(--set run.seed=1)
    local cmd=(.venv/bin/blendsr train -o "$run" --config "$base/config.toml" "${sets[@]}")
    if [ -f "$run/checkpoints/last.pt" ]; then run "${cmd[@]}" --resume; else run "${cmd[@]}"; fi
  done
  local all="('$base', '$IN', '$IN_SEED')"
  await "all(os.path.exists(r + '/summary.json') and ($done)(r).get('step') == 6000 for r in $all)"
  local f=docs/bench/scaling-families/val-inputs-fusesr-l bound="checkpoints/last.pt?residual_clamp=lr-guided"
  [ -s "$f.json" ] || run "$PY" benchmarks/worst_case.py "$DATA" --split val -o "$f" --models \
      "demod-jbu,fusesr-l:$base/$bound,fusesr-l:$IN/$bound,fusesr-l:$IN_SEED/$bound"
  run "$PY" -m gbuffer_export.commands.family_gap "$f.json" --data "$DATA" --by-kind --json "$f-gap.json"
}

# the round's end (docs/training.md, "The scale set's round"), once both curves are scored and every candidate has
# faced the val rule: the test scores of what shipped, every shipped network's margins on val and test (one file per
# model and split; a file written is not scored again), the val record, the rendered set's check, the two curves in
# one table and plot, and the gap of every shipped network on test; then commit what it wrote by hand
SHIPPED=(fusesr fusesr-l fusesr-fast rdg-s fourier-sr nsrd nsrr-fec)
body_end() {
  local markers=("$RUNS/scaling/fusesr.scored" "$RUNS/scaling/fusesr-l.scored" "$FT/released"
                 "$RUNS/scaling/fusesr_470clips/released" "$RUNS/scaling/fusesr-l_470clips/released")
  await "all(__import__('os').path.exists(p) for p in '${markers[*]}'.split())"
  run "$PY" benchmarks/release_weights.py "$DATA" "$RUNS/scaling" --models fusesr,fusesr-l --record-test
  local s m f
  for s in val test; do for m in bicubic demod-bilinear demod-jbu "${SHIPPED[@]/#/pretrained:}"; do
    f=docs/bench/scale/$s-${m#pretrained:}
    [ -s "$f.json" ] || run "$PY" benchmarks/worst_case.py "$DATA" --split $s --models "$m" -o "$f"
  done; done
  run "$PY" benchmarks/worst_case.py "$DATA" --split val -o docs/bench/scale/val --record \
      --scores docs/bench/scale/val-*.json
  run "$PY" benchmarks/worst_case.py "$DATA" --split test -o docs/bench/scale/test --scores docs/bench/scale/test-*.json
  run "$PY" -m training.commands.generate
  run "$PY" -m gbuffer_export.cli validate "$DATA"
  run "$PY" benchmarks/data_scaling.py - --combine docs/bench/scaling-families/fusesr/scaling.json \
      docs/bench/scaling-families/fusesr-l/scaling.json -o docs/bench/scaling-families/combined
  local seen=() n
  for m in "${SHIPPED[@]}"; do n=${m//-/_}; seen+=(--seen-from "pretrained:$m=training/weights/${n}_x4.json"); done
  run "$PY" -m gbuffer_export.commands.family_gap docs/bench/scale/test.json --data "$DATA" --by-kind --unseen-by-all \
      --json docs/bench/scale/gap-test.json "${seen[@]}"
  mark "$RUNS/round-end.done"
}

# JOB: its body in the background under LOGS/JOB.lock, unless that job is running already (DRY: in the foreground)
start() {
  local job=$1 niceness=$NICE
  [ "$job" = render ] && niceness=0
  if [ "${DRY:-0}" = 1 ]; then echo "== $job"; "body_${job//-/_}"; return; fi
  mkdir -p "$LOGS"
  if ! flock -n "$LOGS/$job.lock" true; then echo "$job: running already"; return; fi
  setsid flock -n "$LOGS/$job.lock" bash -c 'echo "$1" > /proc/self/autogroup 2>/dev/null || renice -n "$1" $$ \
      > /dev/null; exec bash "$2" --body "$3"' round "$niceness" "$SELF" "$job" >> "$LOGS/$job.log" 2>&1 < /dev/null &
  echo "$job: started (log $LOGS/$job.log)"
}

if [ "${1:-}" = --body ]; then "body_${2//-/_}"; exit; fi
[ $# -gt 0 ] || set -- "${JOBS[@]}"
for j in "$@"; do
  case " ${JOBS[*]} " in
    *" $j "*) start "$j" ;;
    *) echo "scale_round.sh: unknown job '$j' (${JOBS[*]})" >&2; exit 2 ;;
  esac
done
