#!/bin/sh
# tiny measurement: train on s0 s1 (128x72, 32 frames), test on s2; CPU, 1 thread, nice 15
cd /work/wt13
export PYTHONPATH=$PWD
B="nice -n 15 .venv/bin/python -m gbuffer_export.cli"
D="/tmp/wt13data/s0 /tmp/wt13data/s1"   # clips rendered as in docs/results.md
R=/tmp/wt13data/runs
COMMON="--max-steps 300 --set data.crop=16 --set data.batch_size=4 --set data.val_frames=0 --set run.progress=false --set run.threads=1 --set run.checkpoint_every=1000"
RDG="--config examples/rdg_config.toml --set data.window=7 $COMMON"
FUSE="--config examples/train_config.toml --set optim.warmup_steps=0 $COMMON"
$B train --model rdg-s --data $D -o $R/rdg-s $RDG
$B train --model rdg-s --data $D -o $R/rdg-s-demod $RDG --set model.rdg_demod=true
$B train --model rdg-s --data $D -o $R/rdg-s-nogbuf $RDG --set 'model.rdg_gbuffers=[]'
$B train --model rdg-s --data $D -o $R/rdg-s-nobrdf $RDG --set 'model.rdg_gbuffers=["normal","depth","motion"]'
$B train --model rdg-s --data $D -o $R/rdg-s-nomotion $RDG --set 'model.rdg_gbuffers=["normal","brdf","depth"]'
$B train --model fusesr --data $D -o $R/fusesr $FUSE
$B train --model fusesr-l --data $D -o $R/fusesr-l $FUSE
$B train --model rdg --data $D -o $R/rdg $RDG
$B bench models --data /tmp/wt13data/s2 --threads 1 --flip -o /tmp/wt13data/bench --models bicubic,demod-jbu,fusesr:$R/fusesr/checkpoints/last.pt,fusesr-l:$R/fusesr-l/checkpoints/last.pt,rdg:$R/rdg/checkpoints/last.pt,rdg-s:$R/rdg-s/checkpoints/last.pt,rdg-s:$R/rdg-s-demod/checkpoints/last.pt,rdg-s:$R/rdg-s-nogbuf/checkpoints/last.pt,rdg-s:$R/rdg-s-nobrdf/checkpoints/last.pt,rdg-s:$R/rdg-s-nomotion/checkpoints/last.pt
echo DONE
