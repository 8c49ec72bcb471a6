# The training recipe of each shipped seed network, sourced by benchmarks/zoo.sh (which trains them) and
# benchmarks/wide_seed.sh (which fine-tunes them on the wide dataset): its paper's losses and optimiser
# (examples/*_config.toml, as benchmarks/networks.sh) plus the residual demod-bilinear base (a deviation:
# docs/models/<model>.md, "Base"), and the settings every one of them trains with (LR crop 16, batch 4).
#   recipe MODEL DECAY  prints MODEL's config file, then its --set arguments (DECAY: optim.decay_steps of the
#                       cosine schedules of rdg-s and fusesr-fast); exit status 2 for a model with no recipe here
#   common THREADS      prints the --set arguments every run shares
base() {  # the residual base with a zero-initialised head, as --set arguments for model $1
  echo --set "model.$1.residual=true" --set "model.$1.zero_init_head=true"
}
recipe() {
  case $1 in
    rdg-s) echo examples/rdg_config.toml --set data.window=8 --set model.rdg-s.demod=true "$(base rdg-s)" \
             --set optim.decay_steps="$2" ;;
    nsrd) echo examples/nsrd_config.toml "$(base nsrd)" ;;
    nsrr-fec) echo examples/nsrr_fec_config.toml --set loss.pixel_weight=1.0 "$(base nsrr-fec)" ;;
    # ^ the paper's 1 - SSIM plus an L1 term (a deviation): with 1 - SSIM alone the output's brightness drifted
    #   (val PSNR 13.6 dB after 991 steps, median SR 7-10x the reference; docs/results-history.md, "Shipped networks")
    fourier-sr) echo examples/fourier_sr_config.toml --set optim.lr=5e-4 "$(base fourier-sr)" ;;
    fusesr-fast) echo examples/train_config.toml --set optim.warmup_steps=0 \
                   --set model.fusesr-fast.zero_init_refine=true --set optim.decay_steps="$2" ;;
    *) return 2 ;;
  esac
}
common() {
  echo --set data.crop=16 --set data.batch_size=4 --set data.val_frames=0 --set run.progress=false \
       --set run.threads="$1" --set run.checkpoint_every=100 --set run.keep_checkpoints=3
}
